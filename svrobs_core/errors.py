"""Typed errors of the core and the one shape check (docs/spec.md#validation-errors).

* :class:`SpecError`: a bad experiment or system spec, naming the field; the
  service answers it with HTTP 422, the CLI prints it on one line.
* :class:`DimensionError`: arrays of inconsistent shapes passed to a core
  function. It is a ``ValueError`` but not a ``SpecError``: a spec that
  passed :func:`svrobs_core.parse_spec` never causes one, so reaching it
  from the service is a bug, not the user's mistake.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from .array_types import FloatArray


class SpecError(ValueError):
    """A bad experiment spec or system spec.

    ``field`` is a dotted path into the spec (``"systems[0].A"``, ``"gamma"``),
    so the service can answer HTTP 422 naming it and the CLI can print it.
    """

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


def unknown_field(key: str, known: Iterable[str]) -> str:
    """The message of an unknown field ``key``: ``"unknown field"``, and the known field
    it is a typo of when one is close (``sigmaw``: ``did you mean 'sigma_w'?``)."""
    close = difflib.get_close_matches(key, sorted(known), n=1, cutoff=0.75)
    return f"unknown field (did you mean '{close[0]}'?)" if close else "unknown field"


class DimensionError(ValueError):
    """An array argument of the wrong shape; ``name`` is the argument."""

    def __init__(self, name: str, message: str):
        super().__init__(f"{name} {message}")
        self.name = name
        self.message = message


def check_matrix(
    name: str, array: ArrayLike, shape: Sequence[int | str | None], *, batch: bool = True
) -> FloatArray:
    """``array`` as a float ndarray whose trailing axes have ``shape``, else DimensionError.

    ``shape`` entries: an int (that size), a str (any size, equal for equal
    labels: ``("n", "n")`` is square) or None (any size). ``batch=True``
    allows leading batch axes ``(..., *shape)``; ``batch=False`` wants exactly
    ``shape``. Returns the array (``np.asarray(array, dtype=float)``).
    """
    arr = np.asarray(array, dtype=float)
    k = len(shape)
    ok = arr.ndim >= k if batch else arr.ndim == k
    if ok:
        sizes: dict[str, int] = {}
        for want, got in zip(shape, arr.shape[arr.ndim - k :]):
            if isinstance(want, str):
                want = sizes.setdefault(want, got)
            if want is not None and want != got:
                ok = False
                break
    if not ok:
        dims = ", ".join("." if d is None else str(d) for d in shape)
        lead = "..., " if batch else ""
        raise DimensionError(name, f"must be ({lead}{dims}), got shape {arr.shape}")
    return arr
