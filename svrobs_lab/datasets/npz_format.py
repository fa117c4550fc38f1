"""NPZ archives (``numpy.savez``): ``X`` and ``U``, or ``X_0, U_0, ...``
(docs/datasets.md#npz). Read without pickles; the arrays' declared sizes are
checked before anything is decompressed, and each array's header before its data:
a shape larger than the bytes its member holds, or than the budget once read as
float64, is refused before anything is allocated."""

from __future__ import annotations

import lzma
import math
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from typing import IO, BinaryIO

import numpy as np

from .arrays import rollouts_of
from .parsed import BadDatasetFile, Rollouts

# what numpy.savez and savez_compressed write, and what zipfile also unpacks
COMPRESSION = (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA)
# what reading a damaged or hostile member raises (zipfile, its decompressors, numpy)
READ_ERRORS = (
    ValueError,
    OSError,
    EOFError,
    MemoryError,
    RuntimeError,
    NotImplementedError,
    zipfile.BadZipFile,
    zlib.error,
    lzma.LZMAError,
)


def read_npz(stream: BinaryIO, *, max_array_bytes: int) -> Rollouts:
    return rollouts_of(npz_variables(stream, max_array_bytes=max_array_bytes))


def npz_variables(stream: BinaryIO, *, max_array_bytes: int) -> dict:
    """An NPZ archive's arrays by name (no pickles; sizes checked before unpacking)."""
    try:
        archive = zipfile.ZipFile(stream)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise BadDatasetFile(f"not a readable NPZ (ZIP) archive: {exc}") from None
    with archive:
        members = archive.infolist()
        other = [i.filename for i in members if not i.filename.endswith(".npy")]
        if other:
            hint = " (an Excel workbook? save it as CSV)" if "[Content_Types].xml" in other else ""
            raise BadDatasetFile(
                f"a ZIP archive holding {other[0]!r}, not an NPZ of .npy arrays{hint}"
            )
        total = sum(i.file_size for i in members)
        if total > max_array_bytes:
            raise BadDatasetFile(
                f"the arrays take {total / 2**20:.0f} MB unpacked; at most "
                f"{max_array_bytes / 2**20:.0f} MB"
            )
        keyed = [(info, info.filename[: -len(".npy")]) for info in members]
        for info, key in keyed:
            _check_member(info, key)
        variables = {}
        read_bytes = 0
        for info, key in keyed:
            read_bytes += _checked_size(archive, info, key)
            if read_bytes > max_array_bytes:
                raise BadDatasetFile(
                    f"the arrays take {read_bytes / 2**20:.0f} MB once read; at most "
                    f"{max_array_bytes / 2**20:.0f} MB"
                )
            with _reading(key), archive.open(info) as member:
                variables[key] = np.lib.format.read_array(member, allow_pickle=False)
    return variables


def _check_member(info: zipfile.ZipInfo, key: str) -> None:
    """BadDatasetFile for a member zipfile cannot unpack without a password or a codec."""
    if info.flag_bits & 0x1:
        raise BadDatasetFile(f"{key}: encrypted; save the NPZ without a password")
    if info.compress_type not in COMPRESSION:
        raise BadDatasetFile(
            f"{key}: compression method {info.compress_type} is not supported "
            "(save with numpy.savez or numpy.savez_compressed)"
        )


def _checked_size(archive: zipfile.ZipFile, info: zipfile.ZipInfo, key: str) -> int:
    """The bytes the member's array takes once read as float64 (or as stored, when
    wider), from its .npy header; BadDatasetFile for a pickle, or for a shape the
    member's bytes cannot hold."""
    with _reading(key), archive.open(info) as member:
        shape, dtype, data_start = _header(member)
    if dtype.hasobject:
        raise BadDatasetFile(f"{key}: Python objects (pickles) are not accepted; save numbers")
    count = math.prod(shape)
    declared = count * max(dtype.itemsize, 1)
    held = info.file_size - data_start
    if declared > held:
        raise BadDatasetFile(
            f"{key}: its .npy header declares shape {shape} of {dtype} ({declared:,} bytes) "
            f"but its data is {max(held, 0):,} bytes"
        )
    return count * max(dtype.itemsize, 8)


def _header(member: IO[bytes]) -> tuple[tuple[int, ...], np.dtype, int]:
    """(shape, dtype, where the data starts) of an open .npy member."""
    version = np.lib.format.read_magic(member)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(member)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(member)
    else:
        raise ValueError(f".npy format version {version[0]}.{version[1]} is not supported")
    if any(d < 0 for d in shape):
        raise ValueError(f"negative dimension in shape {shape}")
    return shape, dtype, member.tell()


@contextmanager
def _reading(key: str) -> Iterator[None]:
    """Errors reading the member ``key`` as BadDatasetFile naming it."""
    try:
        yield
    except BadDatasetFile:
        raise
    except READ_ERRORS as exc:
        raise BadDatasetFile(f"{key}: not a readable .npy array: {exc}") from None
