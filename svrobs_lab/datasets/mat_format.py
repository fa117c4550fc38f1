"""MATLAB files: v5 (``save -v7`` and older, read by ``scipy.io.loadmat``) and v7.3
(HDF5, read with h5py) with the variables of the NPZ form (docs/datasets.md#matlab).

MATLAB drops trailing singleton dimensions, so a 2-D ``X`` is (N, T+1) with n = 1
and a 2-D ``U`` is (N, T) with m = 1; rollouts of different lengths go in cell
arrays ``X = {X1, X2, ...}`` (each (T_i+1) x n) or in ``X_0, X_1, ...``. A v7.3
file stores arrays column-major: their axes are reversed on reading (an HDF5 file
without MATLAB's class attributes is read as stored). Sizes are checked before
the arrays are read.
"""

from __future__ import annotations

from typing import BinaryIO

import numpy as np

from .arrays import rollouts_of
from .parsed import BadDatasetFile, Rollouts

NUMERIC_CLASSES = {"double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32"}
NUMERIC_CLASSES |= {"int64", "uint64"}
CELL_VARIABLES = ("X", "U")


def _check_budget(used: int, limit: int) -> None:
    if used > limit:
        raise BadDatasetFile(
            f"the arrays take more than {limit / 2**20:.0f} MB once read (at most "
            f"{limit / 2**20:.0f} MB)"
        )


# -- v5 --------------------------------------------------------------------------------
def read_mat5(stream: BinaryIO, *, max_array_bytes: int) -> Rollouts:
    return rollouts_of(mat5_variables(stream, max_array_bytes=max_array_bytes), matlab=True)


def mat5_variables(stream: BinaryIO, *, max_array_bytes: int) -> dict:
    """A v5 file's variables (numeric arrays; a cell X or U as a list of its arrays)."""
    import scipy.io

    try:
        info = scipy.io.whosmat(stream)
    except Exception as exc:  # noqa: BLE001 - scipy raises many types for a bad file
        raise BadDatasetFile(f"not a readable MATLAB 5 file: {exc}") from None
    used = 0
    for name, shape, cls in info:
        if cls in NUMERIC_CLASSES:
            used += int(np.prod(shape, dtype=np.int64)) * 8
        elif cls in ("struct", "object", "sparse", "function_handle", "opaque"):
            raise BadDatasetFile(f"{name}: a MATLAB {cls}; expected numbers")
    _check_budget(used, max_array_bytes)
    stream.seek(0)
    try:
        data = scipy.io.loadmat(stream, squeeze_me=False, chars_as_strings=True)
    except Exception as exc:  # noqa: BLE001
        raise BadDatasetFile(f"not a readable MATLAB 5 file: {exc}") from None
    return {k: _v5_value(k, v) for k, v in data.items() if not k.startswith("__")}


def _v5_value(name: str, value):
    """A loadmat value: numeric arrays as they are; a cell of X or U as a list of its
    elements (MATLAB's linear order); names' cells stay arrays (arrays.names_of)."""
    if isinstance(value, np.ndarray) and value.dtype == object and name in CELL_VARIABLES:
        return list(value.reshape(-1, order="F"))
    if isinstance(value, np.ndarray) and value.dtype.names is not None:
        raise BadDatasetFile(f"{name}: a MATLAB struct; expected numbers")
    if not isinstance(value, np.ndarray):
        raise BadDatasetFile(f"{name}: a MATLAB {type(value).__name__}; expected numbers")
    return value


# -- v7.3 ------------------------------------------------------------------------------
def read_mat73(stream: BinaryIO, *, max_array_bytes: int) -> Rollouts:
    variables, matlab = mat73_variables(stream, max_array_bytes=max_array_bytes)
    return rollouts_of(variables, matlab=matlab)


def mat73_variables(stream: BinaryIO, *, max_array_bytes: int) -> tuple[dict, bool]:
    """(a v7.3 file's variables, whether MATLAB wrote them: axes reversed, trailing
    singletons dropped)."""
    import h5py

    try:
        f = h5py.File(stream, "r")
    except Exception as exc:  # noqa: BLE001 - h5py raises OSError and others
        raise BadDatasetFile(f"not a readable MATLAB 7.3 (HDF5) file: {exc}") from None
    reader = _H5Reader(f, max_array_bytes)
    with f:
        try:
            variables = {
                k: reader.value(f[k], k, cell_ok=k in CELL_VARIABLES or k.endswith("names"))
                for k in f.keys()
                if not k.startswith("#")  # '#refs#', '#subsystem#': MATLAB's own groups
            }
        except BadDatasetFile:
            raise
        except Exception as exc:  # noqa: BLE001 - a damaged file fails inside h5py
            raise BadDatasetFile(f"not a readable MATLAB 7.3 (HDF5) file: {exc}") from None
    return variables, reader.matlab


class _H5Reader:
    def __init__(self, f, limit: int):
        self.f, self.limit, self.used = f, limit, 0
        self.matlab = False

    def value(self, obj, name: str, *, cell_ok: bool):
        import h5py

        if isinstance(obj, h5py.Group):
            raise BadDatasetFile(f"{name}: a MATLAB struct or object; expected numbers")
        cls = obj.attrs.get("MATLAB_class")
        cls = cls.decode() if isinstance(cls, bytes) else (str(cls) if cls is not None else None)
        self.matlab |= cls is not None
        if obj.attrs.get("MATLAB_empty"):
            return [] if cls == "cell" else np.zeros((0, 0))
        if h5py.check_ref_dtype(obj.dtype) is not None or cls == "cell":
            if not cell_ok:
                raise BadDatasetFile(f"{name}: a cell array; only X, U and names may be cells")
            refs = np.asarray(obj[()]).T.reshape(-1, order="F")
            return [
                self.value(self.f[r], f"{name}{{{i + 1}}}", cell_ok=False)
                for i, r in enumerate(refs)
            ]
        if obj.dtype.names is not None:
            what = "complex numbers" if set(obj.dtype.names) == {"real", "imag"} else "a record"
            raise BadDatasetFile(f"{name}: {what}; expected real numbers")
        self.used += int(obj.size) * 8
        _check_budget(self.used, self.limit)
        data = np.asarray(obj[()])
        if cls is None:
            return data  # plain HDF5: as stored (C order)
        data = data.T
        if cls == "char":
            rows = np.atleast_2d(data)
            return np.array(["".join(map(chr, r)).rstrip() for r in rows.astype(np.int64)])
        if cls == "logical":
            return data.astype(bool)
        return data
