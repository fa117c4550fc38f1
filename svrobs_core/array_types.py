"""Array type aliases of the core's annotations (docs/architecture.md#types).

``FloatArray``: a float64 array (gains, norms, bounds); ``BoolArray``: a mask;
``IntArray``: status codes and indices; ``Array``: any dtype (complex
eigenvalues, object arrays of reasons, arrays whose dtype follows the input).
"""

from __future__ import annotations

from typing import Any, TypeAlias

import numpy as np
from numpy.typing import NDArray

__all__ = ["Array", "BoolArray", "FloatArray", "IntArray"]

Array: TypeAlias = NDArray[Any]
FloatArray: TypeAlias = NDArray[np.float64]
BoolArray: TypeAlias = NDArray[np.bool_]
IntArray: TypeAlias = NDArray[np.integer[Any]]
