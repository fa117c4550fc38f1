"""The context one dataset's stages share (docs/science.md sections 2-8).

:mod:`svrobs_core.pipeline` makes one per dataset; the stage functions read the
spec, system and estimates from it and fill ``out`` (record fields) and ``notes``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .notes import Notes
from .planning import EstimatorAxis
from .spec import ExperimentSpec
from .systems import SystemSpec


@dataclass(kw_only=True)
class Cells:
    """One dataset's context shared by its stages; ``out`` and ``notes`` are filled."""

    spec: ExperimentSpec
    system: SystemSpec
    sigma_w: float
    keys: list[Any]
    axis: EstimatorAxis
    A_hat: np.ndarray
    B_hat: np.ndarray
    out: dict[str, Any]
    notes: Notes
    stage: str = "bounds"  # the stage running (named on an exception, :func:`failed_stage`)
    mc_seconds: float = 0.0  # CPU seconds of the Monte Carlo J

    @property
    def shape(self) -> tuple[int, int]:
        return self.A_hat.shape[:2]
