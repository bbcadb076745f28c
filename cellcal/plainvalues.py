"""Plain Python values from numpy results, for JSON and TOML writers."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np


def plain(value: Any, non_finite: Callable[[float], Any]) -> Any:
    """Dicts (string keys), lists, bools, ints and floats only; ``non_finite(x)``
    replaces NaN and inf, which JSON and TOML cannot hold."""
    if isinstance(value, dict):
        return {str(k): plain(v, non_finite) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v, non_finite) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist(), non_finite)
    if isinstance(value, np.bool_ | bool):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        f = float(value)
        return f if math.isfinite(f) else non_finite(f)
    return value
