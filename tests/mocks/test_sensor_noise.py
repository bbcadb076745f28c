"""The rendered frames' sensor noise (cellcal/mocks/rig/sensor_noise.py): Gaussian, of
the asked σ, independent from pixel to pixel and frame to frame, the same again from the
same seed, on any thread."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from cellcal.mocks.rig.sensor_noise import gaussian_noise


def test_the_noise_is_gaussian_of_the_asked_sigma_and_white() -> None:
    noise = gaussian_noise((1024, 1280), np.random.default_rng(3), 2.0).astype(np.float64)
    assert noise.dtype == np.float64 and noise.shape == (1024, 1280)
    assert abs(noise.mean()) < 0.01
    assert noise.std() == pytest.approx(2.0, rel=0.005)
    kurtosis = np.mean(noise**4) / noise.var() ** 2
    assert kurtosis == pytest.approx(3.0, abs=0.03)
    # 2.5σ and beyond: as often as a normal distribution has them (1.24 %)
    assert np.mean(np.abs(noise) > 5.0) == pytest.approx(0.0124, rel=0.05)
    for a, b in ((noise[:, :-1], noise[:, 1:]), (noise[:-1], noise[1:])):
        assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < 0.005


def test_a_seed_gives_the_same_noise_and_the_next_draw_fresh_noise() -> None:
    first = np.random.default_rng(7)
    a, b = gaussian_noise((50, 60), first, 1.0), gaussian_noise((50, 60), first, 1.0)
    again = np.random.default_rng(7)
    assert np.array_equal(a, gaussian_noise((50, 60), again, 1.0))
    assert np.array_equal(b, gaussian_noise((50, 60), again, 1.0))
    assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < 0.1
    assert gaussian_noise((0, 60), first, 1.0).shape == (0, 60)


def test_threads_drawing_at_once_get_what_one_thread_gets() -> None:
    """The cameras' threads draw their frames' noise together."""
    want = [gaussian_noise((100, 100), np.random.default_rng(k), 2.0) for k in range(4)]
    got: dict[int, bool] = {}

    def draw(k: int) -> None:
        got[k] = all(
            np.array_equal(gaussian_noise((100, 100), np.random.default_rng(k), 2.0), want[k])
            for _ in range(100)
        )

    threads = [threading.Thread(target=draw, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert got == dict.fromkeys(range(4), True)
