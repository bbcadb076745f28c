"""The simulated cell: one ground truth that every simulated device reads.

A robot whose real geometry differs from nominal by seeded errors, each sensor's
pose in the cell, each target's real offset on the flange (the nominal offset in the
configuration is only a guess, off by up to 0.5 mm), and the sensors' noise:

* a point sensor — a laser tracker, or any family whose line of the registry says
  ``simulated_as = "point"`` (``cellcal/families.py``) — stands where
  ``[simulation]`` puts the tracker, with a tracker's noise: 10 µm along the beam
  (distance meter) and 6 µm per metre of range across it (angle encoders), 1σ per
  sample — the class of a FARO / Leica tracker;
* a camera rig (``simulated_as = "images"``) stands where ``[simulation]`` puts the
  rig; no noise model here: its cameras see rendered images (``mocks/rig/twin.py``),
  and their noise is the images' (grey levels, blur).

Same seed, same truth. The noise is drawn per sample, from a generator seeded by the
seed, the noise stream, the sensor, where the robot is (:attr:`SimulatedCell.pose_key`:
the joints and how often the robot has arrived there) and the sample's place in the
pose's series: a re-taken or re-measured sample gets the noise it would have had, so
faults and the threads' order change no number.
"""

from __future__ import annotations

import math
import threading
import zlib
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from cellcal.calib.error_terms import Conditions
from cellcal.calib.geometry import Array, invert
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.robot_model import RobotModel
from cellcal.calib.rotations import matrix_from_euler_xyz
from cellcal.clock import Clock
from cellcal.config import CellConfig
from cellcal.device_options import SensorOptions
from cellcal.families import find
from cellcal.mocks.robot_truth import changed_model, grown_model, perturbed_model, truth_terms
from cellcal.simulation_config import REFERENCE_C


@dataclass(frozen=True)
class SensorTruth:
    """Where a sensor is (T_sensor_base), where its target really is on the flange,
    and a point sensor's noise (σ values in mm; ``point``: it is sampled as a point,
    :meth:`SimulatedCell.sample`)."""

    name: str
    kind: str
    point: bool
    T_sensor_base: Array
    target_offset: Array
    sigma_radial: float
    sigma_transverse_per_mm: float


def _pose(position_mm: list[float], rotation_deg: list[float]) -> Array:
    T = np.eye(4)
    T[:3, :3] = matrix_from_euler_xyz(np.radians(rotation_deg))
    T[:3, 3] = position_mm
    return T


class SimulatedCell:
    """The truth, plus the one piece of state the devices share: where the robot is."""

    def __init__(
        self,
        config: CellConfig,
        nominal: RobotModel,
        seed: int | None = None,
        noise_stream: int = 0,
        clock: Clock | None = None,
    ) -> None:
        sim = config.simulation
        self.faults = sim.faults  # what the twins inject (soaks)
        self.seed = sim.seed if seed is None else seed
        self.noise_stream = noise_stream
        rng = np.random.default_rng(self.seed)
        self.nominal = nominal
        self.model_at_calibration = perturbed_model(
            nominal, rng, length_mm=sim.length_error_mm, angle_deg=sim.angle_error_deg
        )
        self.model = changed_model(self.model_at_calibration, sim.change)
        self.change = sim.change
        # errors beyond geometry, and the payload the robot carries (its compliance's load)
        self.terms = truth_terms(nominal, sim.terms)
        payloads = config.campaign.payloads_kg
        self.payload_kg = float(payloads[0]) if payloads else 0.0
        self.clock = clock  # the campaign's: the temperature profile runs on it
        self.sensors: dict[str, SensorTruth] = {}
        shift = np.eye(4)
        shift[:3, 3] = -np.asarray(sim.change.base_shift_mm, dtype=np.float64)
        for s in config.sensor:
            truth = self._sensor_truth(s, config, rng)
            # the base moved by base_shift_mm: each sensor sits that much the other way
            self.sensors[s.name] = replace(truth, T_sensor_base=truth.T_sensor_base @ invert(shift))
        # Each sample's noise is its own generator's (see the module's note); a resumed
        # campaign draws fresh noise: its stream is the number of poses already stored.
        self._sensor_k = {name: k for k, name in enumerate(self.sensors)}
        self.joint_speed = math.radians(sim.joint_speed_deg_s)
        self.home_deg = list(config.robot.home_deg)
        self.cube_centre_mm = list(config.campaign.cube_centre_mm)
        self.simulation = sim
        self._lock = threading.Lock()
        self._q = np.radians(np.asarray(config.robot.home_deg, dtype=np.float64))
        self._watchers: list[Callable[[Array], None]] = []
        self._visits = PoseVisits()
        self._visits.see(self._q)
        self._fresh: dict[str, tuple[tuple[int, int], int]] = {}  # sample() without first

    @staticmethod
    def _sensor_truth(
        s: SensorOptions, config: CellConfig, rng: np.random.Generator
    ) -> SensorTruth:
        sim = config.simulation
        offset = np.asarray(s.target_offset_mm, dtype=np.float64) + rng.uniform(-0.5, 0.5, 3)
        family = find("sensor", s.kind, s.driver)
        if family is None or family.simulated_as == "point":
            T_base_sensor = _pose(sim.tracker_position_mm, sim.tracker_rotation_deg)
            return SensorTruth(
                s.name,
                s.kind,
                True,
                invert(T_base_sensor),
                offset,
                sim.tracker_radial_um / 1000.0,
                sim.tracker_transverse_um_per_m / 1000.0 / 1000.0,
            )
        T_base_sensor = _pose(sim.rig_position_mm, sim.rig_rotation_deg)
        return SensorTruth(s.name, s.kind, False, invert(T_base_sensor), offset, 0.0, 0.0)

    @property
    def q(self) -> Array:
        with self._lock:
            return self._q.copy()

    @property
    def pose_key(self) -> tuple[int, int]:
        """Where the robot is, as the twins key their noise on it: (a checksum of the
        joints, how often the robot has arrived at them)."""
        with self._lock:
            return self._visits.key

    def set_q(self, q: Array) -> None:
        with self._lock:
            self._q = np.asarray(q, dtype=np.float64).copy()
            self._visits.see(self._q)
            for tell in self._watchers:
                tell(self._q)

    def watch(self, tell: Callable[[Array], None]) -> Callable[[], None]:
        """Call ``tell(q)`` at every move from now on (a twin in another process follows
        the robot so); returns the call that stops it."""
        with self._lock:
            self._watchers.append(tell)
            tell(self._q)

        def unwatch() -> None:
            with self._lock:
                if tell in self._watchers:
                    self._watchers.remove(tell)

        return unwatch

    def flange_pose(self, q: Array) -> Array:
        """What a controller reports: T_base_flange (4×4, mm) from its *nominal*
        kinematics. Each twin converts it to its brand's units and angles."""
        k = target_kinematics(self.nominal, np.atleast_2d(q), np.zeros(3), jacobian=False)
        T: Array = np.eye(4)
        T[:3, :3] = k.R_flange[0]
        T[:3, 3] = k.p[0]
        return T

    def joints_for(self, T_base_flange: Array, q_seed: Array) -> Array | None:
        """The controller's inverse kinematics (nominal model): joints (rad) that put the
        flange at ``T_base_flange`` (4×4, mm), the solution nearest ``q_seed`` turn by
        turn and within the limits when there is one; None when there is none."""
        from cellcal.calib.inverse_kinematics import solve

        seed = np.asarray(q_seed, dtype=np.float64)
        sol = solve(
            self.nominal, np.zeros(3), T_base_flange[None, :3, 3], T_base_flange[:3, :3], seed
        )
        if not sol.ok[0]:
            return None
        q: Array = sol.q[0] + np.round((seed - sol.q[0]) / (2 * np.pi)) * 2 * np.pi
        lo, hi = self.nominal.limits
        return q if ((q >= lo) & (q <= hi)).all() else sol.q[0]

    def target(self, sensor: str) -> CellTarget:
        """The source a protocol-level mock of ``sensor`` serves."""
        return CellTarget(self, sensor)

    def model_now(self) -> RobotModel:
        """The robot's geometry now: after its change, grown with the temperature its
        profile gives at the campaign clock's reading (``[simulation.change]``)."""
        c = self.change
        if c.thermal_mm_per_c == 0 or not c.temperature_c:
            return self.model.with_terms(self.terms)
        t = self.clock.now() if self.clock is not None else 0.0
        grown = grown_model(self.model, c.thermal_mm_per_c * (c.temperature_at(t) - REFERENCE_C))
        return grown.with_terms(self.terms)

    def true_position(self, sensor: str, q: Array | None = None) -> Array:
        """Noise-free target position of ``sensor`` in its frame (mm), the robot's
        geometry as it is now (:meth:`model_now`)."""
        s = self.sensors[sensor]
        qq = self.q if q is None else q
        model = self.model_now()
        q2 = np.atleast_2d(qq)
        load = Conditions(payload_kg=np.full(len(q2), self.payload_kg))
        p = target_kinematics(model, q2, s.target_offset, jacobian=False, conditions=load).p
        out: Array = p @ s.T_sensor_base[:3, :3].T + s.T_sensor_base[:3, 3]
        return out if q is not None and np.ndim(q) == 2 else out[0]

    def sample(self, sensor: str, n: int, first: int | None = None) -> Array:
        """n noisy measurements of a point sensor's target at the robot's current position
        (n×3, mm): samples ``first`` … ``first + n - 1`` of the pose's series, or
        without ``first`` the next ``n`` fresh ones at this pose."""
        s = self.sensors[sensor]
        if not s.point:
            raise ValueError(f"{sensor}: the simulated cell samples point sensors only")
        p = self.true_position(sensor)
        k = self._sensor_k[sensor]
        with self._lock:
            pose, visit = self._visits.key
            if first is None:
                at, drawn = self._fresh.get(sensor, ((0, 0), 0))
                drawn = drawn if at == (pose, visit) else 0
                self._fresh[sensor] = ((pose, visit), drawn + n)
                where, start = 0, drawn
            else:
                where, start = 1, first
        seed = [self.seed, 1, self.noise_stream, k, pose, visit, where]
        z = np.array(
            [np.random.default_rng([*seed, i]).normal(size=3) for i in range(start, start + n)]
        ).reshape(n, 3)
        r = float(np.linalg.norm(p))
        u = p / r
        a = np.cross(u, [0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(u, a)
        st = s.sigma_transverse_per_mm * r
        out: Array = p + np.outer(z[:, 0] * s.sigma_radial, u) + np.outer(z[:, 1] * st, a)
        out += np.outer(z[:, 2] * st, b)
        return out


class PoseVisits:
    """Counts the robot's arrivals at each joint position it is told of: ``key`` is
    (a checksum of the current joints, the arrivals there so far). Positions passed
    through while moving are counted too, but never match a pose the robot stops at."""

    def __init__(self) -> None:
        self._last: bytes | None = None
        self._counts: dict[int, int] = {}
        self.key = (0, 0)

    def see(self, q: Array) -> None:
        raw = np.asarray(q, dtype=np.float64).tobytes()
        if raw == self._last:
            return
        self._last = raw
        crc = zlib.crc32(raw)
        self._counts[crc] = self._counts.get(crc, 0) + 1
        self.key = (crc, self._counts[crc])


class CellTarget:
    """One sensor's target as the simulated cell sees it now (a tracker server's source).

    A tracker's series at one pose may come in parts: the rest after a broken beam or a
    lost link (``MEAS`` of fewer points than the first), or the whole series again.
    The source numbers the samples as the pose's series does — a part of ``n`` points
    after a first request of ``N`` are samples N − n … N − 1 — so each sample's noise is
    the one it would have had in one go."""

    def __init__(self, cell: SimulatedCell, sensor: str) -> None:
        self.cell = cell
        self.sensor = sensor
        self._series: tuple[tuple[int, int], int] | None = None  # pose key, first request

    def sample(self, n: int) -> Array:
        pose = self.cell.pose_key
        if self._series is None or self._series[0] != pose or n >= self._series[1]:
            self._series = (pose, n)
        first = self._series[1] - n
        return self.cell.sample(self.sensor, n, first)
