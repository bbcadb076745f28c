"""``cellcal register``: fit ``T_dst_src`` from common points matched by name."""

from __future__ import annotations

from typing import Any

import click
import numpy as np

from cellcal.calib.geometry import rotation_angle, so3_log
from cellcal.calib.outliers import PointResidual, dominant, point_residuals
from cellcal.calib.registration import METHODS, ROBUST, RigidFit, fit_rigid
from cellcal.calib.registration_batch import LOO_MAX_POINTS, LeaveOneOut, leave_one_out
from cellcal.commands.output import POSITIVE, SEED, print_json, warn
from cellcal.errors import InputError
from cellcal.files.points import MatchedPoints, match_points, read_points


def _names_to_indices(spec: str, names: tuple[str, ...], option: str) -> list[int]:
    wanted = [s.strip() for s in spec.split(",") if s.strip()]
    index = {n: i for i, n in enumerate(names)}
    unknown = [w for w in wanted if w not in index]
    if unknown:
        raise InputError(f"{option}: {', '.join(unknown)} not among the common points")
    return [index[w] for w in wanted]


def _fit(m: MatchedPoints, method: str, **opts: Any) -> RigidFit:
    return fit_rigid(m.src, m.dst, method=method, **opts)


def _report(
    fit: RigidFit, m: MatchedPoints, loo: LeaveOneOut | None, points: tuple[PointResidual, ...]
) -> None:
    deg = np.degrees
    rv = so3_log(fit.R)
    angle = rotation_angle(fit.R)
    axis = rv / np.linalg.norm(rv) if angle > 0 else np.array([0.0, 0.0, 1.0])
    click.echo(f"register: method {fit.method}, {fit.n} common points; T_dst_src maps src into dst")
    for row in fit.T:
        click.echo("  [" + "  ".join(f"{v:14.8f}" for v in row) + " ]")
    click.echo(
        f"rotation {deg(angle):.6f}° about ({axis[0]:.6f}, {axis[1]:.6f}, {axis[2]:.6f}); "
        f"translation ({fit.t[0]:.4f}, {fit.t[1]:.4f}, {fit.t[2]:.4f}) mm"
        + (f"; scale {fit.scale:.9f}" if fit.scale_estimated else "")
    )
    if fit.support_points:
        groups = ["-".join(m.names[i] for i in g) for g in fit.support_points]
        label = "lines A, B" if fit.method == "line" else "points"
        click.echo(f"{label}: {', '.join(groups)}")
    for k, st in enumerate(fit.line_steps, start=1):
        a, b, c = st.axis
        click.echo(
            f"  step {k}: axis ({a:.5g}, {b:.5g}, {c:.5g})  α {deg(st.alpha):.4f}°  "
            f"β {deg(st.beta):.4f}°  θ {deg(st.theta):.6f}°"
        )
    width = max(max(len(n) for n in m.names), len("residuals (mm)"))
    z_of = "leave-one-out" if loo is not None else "residual"
    click.echo(
        f"  {'residuals (mm)':<{width}} {'dx':>11} {'dy':>11} {'dz':>11} {'|d|':>10}  z ({z_of})"
    )
    for p, ok in zip(points, fit.inliers, strict=True):
        flag = "  outlier" if p.outlier else ("  rejected" if not ok else "")
        click.echo(
            f"  {p.name:<{width}} {p.dx:11.4f} {p.dy:11.4f} {p.dz:11.4f} {p.error:10.4f}"
            f"  {p.z:5.1f}{flag}"
        )
    stats = f"RMS {fit.rms:.4f} mm   max {fit.max:.4f} mm"
    if np.isfinite(fit.sigma0):
        stats += f"   σ₀ {fit.sigma0:.4g} (dof {fit.dof})"
    if loo is not None and np.isfinite(loo.rms):
        stats += f"   leave-one-out RMS {loo.rms:.4f} mm"
        if loo.skipped:
            stats += f" ({loo.skipped} point(s) the method needs not left out)"
    click.echo(stats)
    if fit.covariance is not None:
        sd = np.sqrt(np.diag(fit.covariance))
        click.echo(
            f"1σ: rotation ({deg(sd[0]):.2g}, {deg(sd[1]):.2g}, {deg(sd[2]):.2g})°  "
            f"translation at the dst origin ({sd[3]:.3g}, {sd[4]:.3g}, {sd[5]:.3g}) mm   "
            f"condition {fit.condition:.3g}"
        )


@click.command()
@click.option("--src", "src_path", required=True, help="CSV name,x,y,z (mm) in the source frame.")
@click.option("--dst", "dst_path", required=True, help="CSV name,x,y,z (mm) in the target frame.")
@click.option(
    "--method",
    type=click.Choice(METHODS),
    default="svd",
    show_default=True,
    help="svd: least squares (Kabsch); quaternion: Horn; three-point; rodrigues: Cayley "
    "iterated (rodrigues-linear: one solve); small-angle: linearised, iterated; line: the "
    "paper's characteristic-line method.",
)
@click.option("--line-a", help="line method: names of the points on line A, e.g. P1,P2.")
@click.option("--line-b", help="line method: names of the points on line B, e.g. P2,P3.")
@click.option("--points", "three", help="three-point method: the three names to use.")
@click.option("--scale", is_flag=True, help="Also fit a uniform scale (least-squares methods).")
@click.option("--robust", type=click.Choice(ROBUST), help="Down-weight or reject outliers.")
@click.option("--ransac-threshold", type=POSITIVE, help="RANSAC inlier distance (mm).")
@click.option(
    "--weighted",
    is_flag=True,
    help="Weight points by the sx,sy,sz columns (1σ, mm) of either or both files.",
)
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed for RANSAC.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def register(
    src_path: str,
    dst_path: str,
    method: str,
    line_a: str | None,
    line_b: str | None,
    three: str | None,
    scale: bool,
    robust: str | None,
    ransac_threshold: float | None,
    weighted: bool,
    seed: int,
    as_json: bool,
) -> None:
    """Fit T_dst_src from common points matched by name."""
    # Options that contradict each other are refused before any file is read.
    if ransac_threshold is not None and robust != "ransac":
        raise InputError("--ransac-threshold needs --robust ransac")
    if (line_a is None) != (line_b is None):
        raise InputError("give both --line-a and --line-b, or neither")
    if line_a is not None and method != "line":
        raise InputError("--line-a/--line-b need --method line")
    if three is not None and method != "three-point":
        raise InputError("--points needs --method three-point")
    m = match_points(read_points(src_path), read_points(dst_path))
    opts: dict[str, Any] = {"scale": scale, "robust": robust, "seed": seed}
    if ransac_threshold is not None:
        opts["ransac_threshold"] = ransac_threshold
    if line_a is not None and line_b is not None:
        opts["lines"] = (
            _names_to_indices(line_a, m.names, "--line-a"),
            _names_to_indices(line_b, m.names, "--line-b"),
        )
    if three is not None:
        picked = _names_to_indices(three, m.names, "--points")
        if len(picked) != 3 or len(set(picked)) != 3:
            raise InputError("--points: give three different point names, e.g. P1,P2,P3")
        opts["three_points"] = picked
    if weighted:
        if m.src_sigma is None and m.dst_sigma is None:
            raise InputError("--weighted: neither file has sx,sy,sz columns")
        opts["cov_src"] = m.src_sigma
        opts["cov_dst"] = m.dst_sigma
    fit = _fit(m, method, **opts)
    loo = None
    if 4 <= m.src.shape[0] <= LOO_MAX_POINTS and robust is None:
        loo = leave_one_out(m.src, m.dst, method=method, **opts)
    points = point_residuals(
        m.names, fit.residuals, None if loo is None or not np.isfinite(loo.rms) else loo.norms
    )
    hints = []
    top = dominant(points)
    if top is not None and robust is None:
        share = 100.0 * top.error**2 / sum(p.error**2 for p in points)
        hints.append(
            f"point {top.name} carries {share:.0f} % of the squared error: re-measure it, or "
            "try --robust huber (or --robust ransac)"
        )
    # Warnings only once the fit stands: an error is always the one line on stderr.
    for w in (*m.warnings, *fit.warnings, *hints):
        warn(w)
    if as_json:
        cov = fit.covariance
        sd = None if cov is None else np.sqrt(np.diag(cov))
        print_json(
            {
                "method": fit.method,
                "T": fit.T,
                "rms_mm": fit.rms,
                "max_mm": fit.max,
                "residuals_mm": fit.residual_norms,
                "names": list(m.names),
                "residual_vectors_mm": fit.residuals,
                "inliers": fit.inliers,
                "scale": fit.scale,
                "rotation_deg": float(np.degrees(rotation_angle(fit.R))),
                "rotation_vector_deg": np.degrees(so3_log(fit.R)),
                "translation_mm": fit.t,
                "sigma0": fit.sigma0,
                "dof": fit.dof,
                "loo_rms_mm": None if loo is None else loo.rms,
                "loo_residuals_mm": None if loo is None else loo.norms,
                "rotation_std_deg": None if sd is None else np.degrees(sd[:3]),
                "translation_std_mm": None if sd is None else sd[3:],
                "condition_number": fit.condition,
                "support_points": [[m.names[i] for i in g] for g in fit.support_points],
                "points": [p.as_dict() for p in points],
                "outliers": [p.name for p in points if p.outlier],
                "warnings": list(m.warnings) + list(fit.warnings) + hints,
            }
        )
    else:
        _report(fit, m, loo, points)
