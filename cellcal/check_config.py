"""The ``[check]`` table: how a check between calibrations is made and judged
(``calib/drift.py``, ``campaign/check_kind.py``)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, model_validator

from cellcal.device_options import Strict

#: a check's poses: enough for the causes it tells apart (a base moved: 6 parameters)
MIN_POSES, MAX_POSES, DEFAULT_POSES = 6, 200, 12


class CheckConfig(Strict):
    """``poses``: how many a check measures; the limits are ``warning_factor`` and
    ``recalibrate_factor`` × the 1σ RMS error the model predicts for them (or the spread
    of earlier checks, where larger)."""

    poses: Annotated[int, Field(ge=MIN_POSES, le=MAX_POSES)] = DEFAULT_POSES
    warning_factor: Annotated[float, Field(gt=0, le=100)] = 2.0
    recalibrate_factor: Annotated[float, Field(gt=0, le=100)] = 3.0

    @model_validator(mode="after")
    def _ordered(self) -> CheckConfig:
        if self.recalibrate_factor < self.warning_factor:
            raise ValueError(
                f"recalibrate_factor {self.recalibrate_factor:g} is below warning_factor "
                f"{self.warning_factor:g}"
            )
        return self
