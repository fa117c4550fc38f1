"""NPZ archives (``numpy.savez``): ``X`` and ``U``, or ``X_0, U_0, ...``
(docs/datasets.md#npz). Read without pickles; the arrays' declared sizes are
checked before anything is decompressed."""

from __future__ import annotations

import zipfile
import zlib
from typing import BinaryIO

import numpy as np

from .arrays import rollouts_of
from .parsed import BadDatasetFile, Rollouts


def read_npz(stream: BinaryIO, *, max_array_bytes: int) -> Rollouts:
    return rollouts_of(npz_variables(stream, max_array_bytes=max_array_bytes))


def npz_variables(stream: BinaryIO, *, max_array_bytes: int) -> dict:
    """An NPZ archive's arrays by name (no pickles; sizes checked before unpacking)."""
    try:
        members = zipfile.ZipFile(stream).infolist()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise BadDatasetFile(f"not a readable NPZ (ZIP) archive: {exc}") from None
    other = [i.filename for i in members if not i.filename.endswith(".npy")]
    if other:
        hint = " (an Excel workbook? save it as CSV)" if "[Content_Types].xml" in other else ""
        raise BadDatasetFile(f"a ZIP archive holding {other[0]!r}, not an NPZ of .npy arrays{hint}")
    total = sum(i.file_size for i in members)
    if total > max_array_bytes:
        raise BadDatasetFile(
            f"the arrays take {total / 2**20:.0f} MB unpacked; at most "
            f"{max_array_bytes / 2**20:.0f} MB"
        )
    stream.seek(0)
    variables = {}
    try:
        npz = np.load(stream, allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise BadDatasetFile(f"not a readable NPZ archive: {exc}") from None
    with npz:
        for key in npz.files:
            try:
                variables[key] = npz[key]
            except ValueError as exc:
                if "allow_pickle" in str(exc):
                    raise BadDatasetFile(
                        f"{key}: Python objects (pickles) are not accepted; save numbers"
                    ) from None
                raise BadDatasetFile(f"{key}: not a readable .npy array: {exc}") from None
            except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
                raise BadDatasetFile(f"{key}: not a readable .npy array: {exc}") from None
    return variables
