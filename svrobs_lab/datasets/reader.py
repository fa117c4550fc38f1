"""An uploaded file -> :class:`ParsedDataset`: its format told from its first bytes
(docs/datasets.md#formats), read by that format's reader, checked by
:func:`~svrobs_lab.datasets.parsed.build`.

A file is never loaded whole to find its format or its digest: the sha256 is
computed over 1 MiB reads, and only the first kilobyte is looked at to choose
the reader.
"""

from __future__ import annotations

import codecs
import hashlib
import os
from typing import BinaryIO

from svrobs_core.errors import SpecError

from .csv_format import read_csv
from .json_format import read_json
from .mat_format import read_mat5, read_mat73
from .npz_format import read_npz
from .parsed import BadDatasetFile, DatasetOptions, ParsedDataset, build

READ_BYTES = 1 << 20
# the arrays a file decodes to may take at most this many times the upload limit
# (a CSV of one-digit numbers is a quarter of its float64 arrays)
ARRAY_FACTOR = 4
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
FORMAT_NAMES = {
    "csv": "CSV",
    "npz": "NPZ",
    "mat": "MATLAB v5",
    "mat73": "MATLAB v7.3",
    "json": "JSON",
}
# what other common files start with, to name them in the error
_OTHER_MAGIC = (
    (b"\x89PNG", "a PNG image"),
    (b"%PDF", "a PDF document"),
    (b"\x1f\x8b", "a gzip archive (unpack it first)"),
    (b"PAR1", "a Parquet file (save it as CSV)"),
    (b"\xd0\xcf\x11\xe0", "an Excel 97-2003 workbook (save it as CSV)"),
    (b"\x93NUMPY", "a .npy file of one array (save X and U together with numpy.savez)"),
    (b"7z\xbc\xaf", "a 7z archive"),
    (b"BZh", "a bzip2 archive (unpack it first)"),
    (b"\xfd7zXZ", "an xz archive (unpack it first)"),
)


def digest(stream: BinaryIO) -> tuple[str, int]:
    """(sha256 hex, size in bytes) of the whole stream, read from the start."""
    stream.seek(0)
    h, size = hashlib.sha256(), 0
    while chunk := stream.read(READ_BYTES):
        h.update(chunk)
        size += len(chunk)
    stream.seek(0)
    return h.hexdigest(), size


def detect(head: bytes, filename: str | None = None) -> str:
    """The format of a file from its first bytes: csv, npz, mat, mat73 or json;
    BadDatasetFile naming what it is otherwise."""
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        return "npz"
    if head.startswith(b"MATLAB 7.3 MAT-file") or HDF5_SIGNATURE in (head[:8], head[512:520]):
        return "mat73"
    if head.startswith(b"MATLAB 5.0 MAT-file"):
        return "mat"
    ext = os.path.splitext(filename or "")[1].lower()
    named = f" {ext!r}" if ext else ""
    for magic, what in _OTHER_MAGIC:
        if head.startswith(magic):
            raise BadDatasetFile(f"unknown format{named}: {what}; {_accepted()}")
    text = _text_start(head)
    if text is None:
        hint = " (MATLAB v4? save with -v7 or -v7.3)" if ext == ".mat" else ""
        raise BadDatasetFile(f"unknown format{named}: binary data{hint}; {_accepted()}")
    if text.lstrip("\ufeff \t\r\n").startswith(("{", "[")):
        return "json"
    if ext in (".xlsx", ".xls", ".ods", ".parquet", ".h5", ".hdf5", ".npy", ".pkl"):
        raise BadDatasetFile(f"unknown format{named}; {_accepted()}")
    return "csv"


def _accepted() -> str:
    return "upload CSV, NPZ, MATLAB (.mat v5 or v7.3) or JSON"


def _text_start(head: bytes) -> str | None:
    """``head`` decoded as UTF-8 (bytes that are not UTF-8 kept as surrogates), or None
    when it is not text: control bytes other than tab and line ends (binary data has
    them: a kilobyte of random bytes has none with probability 1e-60). Text in another
    encoding (Latin-1 from a spreadsheet) is text: the CSV reader names the row and
    column of its first byte that is not UTF-8."""
    text = codecs.getincrementaldecoder("utf-8")("surrogateescape").decode(head, final=False)
    if any(ord(c) < 32 and c not in "\t\r\n" for c in text):
        return None
    return text


def check_options(fmt: str, options: DatasetOptions) -> None:
    """The upload fields that do not apply to the file's format are errors naming them."""
    if fmt == "csv":
        for field in ("state_names", "input_names"):
            if getattr(options, field) is not None:
                column = field.replace("names", "columns")
                raise SpecError(
                    field, f"a CSV file names its channels by its columns: give {column}"
                )
        return
    for field in ("state_columns", "input_columns"):
        if getattr(options, field) is not None:
            names = field.replace("columns", "names")
            raise SpecError(
                field,
                f"only for CSV files; name the channels of a {FORMAT_NAMES[fmt]} file with {names}",
            )


def parse_dataset(
    stream: BinaryIO,
    *,
    filename: str | None = None,
    options: DatasetOptions | None = None,
    max_bytes: int,
) -> ParsedDataset:
    """Read an uploaded file (a seekable binary stream) into a ParsedDataset.

    ``max_bytes`` is the upload limit (SVROBS_MAX_DATASET_MB): the arrays a file
    decodes to may take at most ARRAY_FACTOR times that. Raises BadDatasetFile
    (field ``file``) or SpecError naming the upload field."""
    options = options or DatasetOptions()
    sha256, size = digest(stream)
    if size == 0:
        raise BadDatasetFile("the file is empty")
    head = stream.read(1024)
    stream.seek(0)
    fmt = detect(head, filename)
    check_options(fmt, options)
    limit = ARRAY_FACTOR * max_bytes
    if fmt == "csv":
        rollouts = read_csv(stream, options, max_array_bytes=limit)
    elif fmt == "npz":
        rollouts = read_npz(stream, max_array_bytes=limit)
    elif fmt == "mat":
        rollouts = read_mat5(stream, max_array_bytes=limit)
    elif fmt == "mat73":
        rollouts = read_mat73(stream, max_array_bytes=limit)
    else:
        rollouts = read_json(stream, size=size)
    return build(
        rollouts, options, fmt=fmt, sha256=sha256, size_bytes=size, names_in_file=fmt == "csv"
    )
