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

import io
import struct
import zlib
from typing import BinaryIO

import numpy as np

from .arrays import rollouts_of
from .parsed import BadDatasetFile, Rollouts

NUMERIC_CLASSES = {"double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32"}
NUMERIC_CLASSES |= {"int64", "uint64"}
CELL_VARIABLES = ("X", "U")
MI_COMPRESSED = 15  # a v5 data element's type: a zlib stream of one variable
INFLATE_STEP = 2**20  # bytes inflated at a time while a compressed variable is measured


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
        if cls in ("struct", "object", "sparse", "function_handle", "opaque"):
            raise BadDatasetFile(f"{name}: a MATLAB {cls}; expected numbers")
        if cls != "cell":  # a cell's contents are counted by _mat5_data_bytes
            used += int(np.prod(shape, dtype=np.int64)) * 8
    _check_budget(used, max_array_bytes)
    _check_budget(_mat5_data_bytes(stream, max_array_bytes), max_array_bytes)
    stream.seek(0)
    try:
        data = scipy.io.loadmat(stream, squeeze_me=False, chars_as_strings=True)
    except Exception as exc:  # noqa: BLE001
        raise BadDatasetFile(f"not a readable MATLAB 5 file: {exc}") from None
    return {k: _v5_value(k, v) for k, v in data.items() if not k.startswith("__")}


def _mat5_data_bytes(stream: BinaryIO, limit: int) -> int:
    """The bytes of a v5 file's data elements once inflated (a cell's contents too),
    counted a piece at a time without keeping them: a few kB of zlib stream can
    inflate to gigabytes. Counting stops past ``limit``. 0 for a file without a v5
    header (MATLAB 4: no compression, no cells)."""
    stream.seek(0)
    head = stream.read(128)
    order = {b"IM": "<", b"MI": ">"}.get(head[126:128])
    if len(head) < 128 or order is None:
        return 0
    total = 0
    while total <= limit:
        tag = stream.read(8)
        if len(tag) < 8:
            break
        kind, nbytes = struct.unpack(order + "II", tag)
        if kind == MI_COMPRESSED:
            total += _inflated_bytes(stream, nbytes, limit - total)
        else:
            total += nbytes
            stream.seek(nbytes + (-nbytes % 8), io.SEEK_CUR)
    return total


def _inflated_bytes(stream: BinaryIO, nbytes: int, room: int) -> int:
    """The inflated size of the next ``nbytes`` of zlib stream, or a number above
    ``room`` as soon as it passes it."""
    inflate, out, left = zlib.decompressobj(), 0, nbytes
    try:
        while left > 0 and out <= room:
            data = stream.read(min(left, INFLATE_STEP))
            if not data:
                break
            left -= len(data)
            while data and out <= room:
                out += len(inflate.decompress(data, INFLATE_STEP))
                data = inflate.unconsumed_tail
    except zlib.error as exc:
        raise BadDatasetFile(f"not a readable MATLAB 5 file: {exc}") from None
    return out


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
                k: reader.value(
                    _in_file(f, k), k, cell_ok=k in CELL_VARIABLES or k.endswith("names")
                )
                for k in f.keys()
                if not k.startswith("#")  # '#refs#', '#subsystem#': MATLAB's own groups
            }
        except BadDatasetFile:
            raise
        except Exception as exc:  # noqa: BLE001 - a damaged file fails inside h5py
            raise BadDatasetFile(f"not a readable MATLAB 7.3 (HDF5) file: {exc}") from None
    return variables, reader.matlab


def _in_file(f, name: str):
    """The object a name of the file links to: only a link inside the file (an HDF5
    file can name objects, and data, in other files of the server)."""
    import h5py

    if not isinstance(f.get(name, getlink=True), h5py.HardLink):
        raise BadDatasetFile(f"{name}: a link to another file; expected numbers")
    return f[name]


def _h5_outside(obj) -> bool:
    """Whether a dataset's data are kept outside the file (external storage or a
    virtual dataset): never read, they could be any file of the server."""
    return bool(obj.is_virtual or obj.id.get_create_plist().get_external_count() > 0)


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
        if _h5_outside(obj):
            raise BadDatasetFile(f"{name}: data kept outside the file; expected numbers")
        if obj.attrs.get("MATLAB_empty"):
            return [] if cls == "cell" else np.zeros((0, 0))
        is_ref = h5py.check_ref_dtype(obj.dtype) is not None
        if is_ref or cls == "cell":
            if not cell_ok:
                raise BadDatasetFile(f"{name}: a cell array; only X, U and names may be cells")
            if not is_ref:
                raise BadDatasetFile(f"{name}: a cell array that holds no cells")
            self._count(obj)
            refs = np.asarray(obj[()]).T.reshape(-1, order="F")
            return [
                self.value(self.f[r], f"{name}{{{i + 1}}}", cell_ok=False)
                for i, r in enumerate(refs)
            ]
        if obj.dtype.names is not None:
            what = "complex numbers" if set(obj.dtype.names) == {"real", "imag"} else "a record"
            raise BadDatasetFile(f"{name}: {what}; expected real numbers")
        # numbers (MATLAB's char is uint16) or text (a plain HDF5 file's names; a
        # variable-length string lives in the file's heap, so the file bounds it)
        if obj.dtype.kind not in "biufS" and h5py.check_string_dtype(obj.dtype) is None:
            raise BadDatasetFile(f"{name}: {obj.dtype} values; expected numbers")
        self._count(obj)
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

    def _count(self, obj) -> None:
        """Add a dataset's size once read (as float64, or wider) before reading it."""
        self.used += int(obj.size) * max(8, obj.dtype.itemsize)
        _check_budget(self.used, self.limit)
