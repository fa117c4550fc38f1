"""The context one dataset's stages share (docs/science.md sections 2-8).

:mod:`svrobs_core.pipeline` makes one per dataset; the stage functions read the
spec, system and estimates from it and fill ``out`` (record fields) and ``notes``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeAlias, TypeVar

import numpy as np

from .array_types import FloatArray
from .notes import Notes
from .planning import EstimatorAxis
from .spec import ExperimentSpec
from .systems import SystemSpec


class ObserverModel(Protocol):
    """What every stage reads of the system: C and the noise levels (a true
    system, or the observer model of measured data, docs/measured.md#records)."""

    @property
    def C(self) -> FloatArray: ...
    @property
    def sigma_u(self) -> float: ...
    @property
    def sigma_v(self) -> float: ...


SystemT = TypeVar("SystemT", bound=ObserverModel)
SigmaT = TypeVar("SigmaT")


@dataclass(kw_only=True)
class StageCells(Generic[SystemT, SigmaT]):
    """One dataset's context shared by its stages; ``out`` and ``notes`` are filled."""

    spec: ExperimentSpec
    system: SystemT
    sigma_w: SigmaT
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


# A simulated dataset's: its true system and one sigma_w.
Cells: TypeAlias = StageCells[SystemSpec, float]
