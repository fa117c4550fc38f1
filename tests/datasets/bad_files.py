"""Kinds of bad dataset upload, each with the one 422 it must get: (id, file name,
bytes, extra form fields, the field named, a regular expression of the message)."""

from __future__ import annotations

import io
import struct
import zipfile

import numpy as np

from tests.datasets import files

X, U = files.rollouts(seed=11, lengths=(4, 3, 5))
GOOD_CSV = files.csv_bytes(X, U)
CSV_LINES = GOOD_CSV.decode().splitlines()  # header, then rows 2.. of rollouts 0, 1, 2


def _csv(edit) -> bytes:
    lines = list(CSV_LINES)
    edit(lines)
    # a lone surrogate \udcXX is written as the byte 0xXX (not UTF-8)
    return ("\n".join(lines) + "\n").encode("utf-8", "surrogateescape")


def _set(row: int, column: int, value: str):
    def edit(lines):
        cells = lines[row - 1].split(",")
        cells[column] = value
        lines[row - 1] = ",".join(cells)

    return edit


def _add_column(lines):
    lines[0] += ",temp"
    for i in range(1, len(lines)):
        lines[i] += ",20"


def _rename(old: str, new: str):
    def edit(lines):
        lines[0] = lines[0].replace(old, new)

    return edit


def _npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _pickled_npz() -> bytes:
    buf = io.BytesIO()
    np.savez(buf, X=np.array([np.zeros((3, 2)), np.zeros((4, 2))], dtype=object))
    return buf.getvalue()


def _npz_declaring(shape: tuple[int, ...]) -> bytes:
    """An NPZ whose X.npy header declares ``shape`` of float64 over 64 bytes of data."""
    header = repr({"descr": "<f8", "fortran_order": False, "shape": shape}).encode()
    header += b" " * (-(10 + len(header) + 1) % 64) + b"\n"
    npy = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + bytes(64)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("X.npy", npy)
    return buf.getvalue()


def _npz_marked(*, flags: int = 0, method: int = zipfile.ZIP_STORED) -> bytes:
    """A good NPZ whose X.npy is marked, in its local and central headers, with the
    general purpose ``flags`` (1: encrypted) and the compression ``method``."""
    data = bytearray(_npz(X=np.zeros((1, 3, 1))))
    for signature, at in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):
        start = data.find(signature) + at
        (old,) = struct.unpack_from("<H", data, start)
        struct.pack_into("<HH", data, start, old | flags, method)
    return bytes(data)


def _xlsx() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("[Content_Types].xml", "<Types/>")
        z.writestr("xl/workbook.xml", "<workbook/>")
    return buf.getvalue()


def _mat_struct() -> bytes:
    import scipy.io

    buf = io.BytesIO()
    scipy.io.savemat(buf, {"X": {"a": np.zeros((2, 2))}})
    return buf.getvalue()


def _mat(**variables) -> bytes:
    import scipy.io

    buf = io.BytesIO()
    scipy.io.savemat(buf, variables)
    return buf.getvalue()


def _mat73_complex() -> bytes:
    import tempfile
    from pathlib import Path

    import hdf5storage

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "c.mat"
        hdf5storage.savemat(
            str(path), {"X": np.ones((2, 4, 3)) * (1 + 2j)}, format="7.3", matlab_compatible=True
        )
        return path.read_bytes()


def _json(text: str) -> bytes:
    return text.encode()


def cases() -> list[tuple]:
    """Every kind: rows are the file's lines (header = row 1); rollout 0 is rows 2-6,
    rollout 1 rows 7-10, rollout 2 rows 11-16; columns: rollout, k, x1, x2, x3, u1, u2."""
    nan_X = [x.copy() for x in X]
    nan_X[1][2, 1] = np.inf
    return [
        (
            "csv-not-a-number",
            "d.csv",
            _csv(_set(4, 4, "abc")),
            {},
            "file",
            r"^row 4, column x3: 'abc' is not a number$",
        ),
        (
            "csv-k-jump",
            "d.csv",
            _csv(_set(9, 1, "3")),
            {},
            "file",
            r"^rollout 1: k jumps from 1 to 3 \(row 9\)",
        ),
        (
            "csv-nan",
            "d.csv",
            _csv(_set(5, 5, "nan")),
            {},
            "file",
            r"^NaN at rollout 0, k 3, column u1 \(row 5: 'nan'\)$",
        ),
        (
            "csv-field-count",
            "d.csv",
            _csv(_set(3, 6, "1,2")),
            {},
            "file",
            r"^row 3: 8 fields, the header has 7$",
        ),
        (
            "csv-no-rollout-column",
            "d.csv",
            _csv(_rename("rollout", "run")),
            {},
            "file",
            r"^header: no 'rollout' column",
        ),
        (
            "csv-rollout-split",
            "d.csv",
            _csv(_set(12, 0, "0")),
            {},
            "file",
            r"^row 12, column rollout: rollout 0 appears again after rollout 2",
        ),
        (
            "csv-one-row-rollout",
            "d.csv",
            _csv(lambda ls: ls.append("3,0,1,2,3,,")),
            {},
            "file",
            r"^rollout 3: 1 row; a rollout needs at least 2 states",
        ),
        (
            "csv-unknown-column",
            "d.csv",
            _csv(_add_column),
            {},
            "file",
            r"^header: column 'temp' is not rollout, k, x1\.\.xn or u1\.\.um",
        ),
        (
            "csv-missing-state",
            "d.csv",
            _csv(_rename("x2", "x4")),
            {},
            "file",
            r"^header: state column x2 is missing \(x1, x3, x4 given\)$",
        ),
        (
            "csv-empty-input",
            "d.csv",
            _csv(_set(3, 6, "")),
            {},
            "file",
            r"^row 3, column u2: empty \(only a rollout's last row may leave its inputs empty\)$",
        ),
        (
            "csv-not-utf8",
            "d.csv",
            _csv(_set(3, 2, "1.5\udce9")),
            {},
            "file",
            r"^row 3, column x1: not UTF-8 text \(byte 0xe9\)$",
        ),
        (
            # a small file in Latin-1 (a spreadsheet's export): one in eight bytes is not
            # UTF-8, and it is text all the same
            "csv-latin1",
            "d.csv",
            "rollout,k,x1,u1\nessai-été,0,1,1\nessai-été,1,2,\n".encode("latin-1"),
            {},
            "file",
            r"^row 2, column rollout: not UTF-8 text \(byte 0xe9\)$",
        ),
        (
            "csv-k-not-integer",
            "d.csv",
            _csv(_set(2, 1, "0.5")),
            {},
            "file",
            r"^row 2, column k: '0\.5' is not an integer$",
        ),
        (
            "csv-header-only",
            "d.csv",
            (CSV_LINES[0] + "\n").encode(),
            {},
            "file",
            r"^the CSV file has a header but no rows$",
        ),
        (
            "npz-2d",
            "d.npz",
            _npz(X=np.zeros((5, 3))),
            {},
            "file",
            r"^X: expected 3 dimensions \(rollouts, T\+1, n\), got 2$",
        ),
        (
            "npz-u-shape",
            "d.npz",
            _npz(X=np.zeros((2, 5, 3)), U=np.zeros((2, 5, 1))),
            {},
            "file",
            r"^U: shape \(2, 5, 1\) does not match X \(2, 5, 3\): expected \(2, 4, m\)$",
        ),
        (
            "npz-pickle",
            "d.npz",
            _pickled_npz(),
            {},
            "file",
            r"^X: Python objects \(pickles\) are not accepted",
        ),
        (
            "npz-missing-rollout",
            "d.npz",
            _npz(X_0=X[0], U_0=U[0], X_2=X[2], U_2=U[2]),
            {},
            "file",
            r"^X_1 is missing \(X_0 \.\. X_2 are expected\)$",
        ),
        (
            "npz-unknown-variable",
            "d.npz",
            _npz(X=np.zeros((2, 5, 3)), Y=np.zeros(3)),
            {},
            "file",
            r"^unknown variable 'Y'",
        ),
        (
            "npz-inf",
            "d.npz",
            files.npz_bytes(nan_X, U),
            {},
            "file",
            r"^inf at rollout 1, k 2, column x2$",
        ),
        (
            "npz-text",
            "d.npz",
            _npz(X=np.array([[["a", "b"], ["c", "d"]]])),
            {},
            "file",
            r"^X: expected numbers, got text$",
        ),
        (
            "npz-shape-over-its-data",
            "d.npz",
            _npz_declaring((10**12, 1, 1)),
            {},
            "file",
            r"^X: its \.npy header declares shape \(1000000000000, 1, 1\) of float64 "
            r"\(8,000,000,000,000 bytes\) but its data is 64 bytes$",
        ),
        (
            "npz-encrypted",
            "d.npz",
            _npz_marked(flags=0x1),
            {},
            "file",
            r"^X: encrypted; save the NPZ without a password$",
        ),
        (
            "npz-compression-method",
            "d.npz",
            _npz_marked(method=99),
            {},
            "file",
            r"^X: compression method 99 is not supported",
        ),
        ("mat-struct", "d.mat", _mat_struct(), {}, "file", r"^X: a MATLAB struct"),
        (
            "mat-empty-cell",
            "d.mat",
            _mat(X=np.empty((0,), dtype=object)),
            {},
            "file",
            r"^X: an empty cell array \(no rollouts\)$",
        ),
        ("mat-empty", "d.mat", _mat(X=np.empty((0, 0))), {}, "file", r"^no rollouts$"),
        (
            "mat-truncated",
            "d.mat",
            files.mat5_bytes(X, U)[:300],
            {},
            "file",
            r"^not a readable MATLAB 5 file",
        ),
        (
            "mat73-complex",
            "c.mat",
            _mat73_complex(),
            {},
            "file",
            r"^X: complex numbers; expected real numbers$",
        ),
        (
            "json-syntax",
            "d.json",
            _json('{"X": [[[1, 2], [3, 4]]'),
            {},
            "file",
            r"^not valid JSON: .* at line 1, column \d+$",
        ),
        (
            "json-nan",
            "d.json",
            _json('{"X": [[[1, NaN], [3, 4]]]}'),
            {},
            "file",
            r"^NaN is not a number JSON allows",
        ),
        (
            "json-ragged",
            "d.json",
            _json('{"X": [[[1, 2, 3], [3, 4]]]}'),
            {},
            "file",
            r"^X\[0\]\[1\]: 2 numbers, X\[0\]\[0\] has 3$",
        ),
        (
            "json-string",
            "d.json",
            _json('{"X": [[[1, "2"], [3, 4]]]}'),
            {},
            "file",
            r'^X\[0\]\[0\]\[1\]: "2" is not a number$',
        ),
        (
            "json-lists",
            "d.json",
            _json('{"X": [[' + ",".join(["[1]"] * 2_000_000) + "]]}"),
            {},
            "file",
            r"^a JSON dataset has at most 2,000,000 lists \(rows and rollouts\), this one "
            r"about 2,000,002; upload larger sets as CSV, NPZ or MAT$",
        ),
        (
            "png",
            "plot.png",
            b"\x89PNG\r\n\x1a\n" + bytes(100),
            {},
            "file",
            r"^unknown format '\.png': a PNG image",
        ),
        (
            "xlsx",
            "book.xlsx",
            _xlsx(),
            {},
            "file",
            r"^a ZIP archive holding '\[Content_Types\]\.xml', not an NPZ .*Excel",
        ),
        (
            "binary",
            "d.bin",
            bytes(range(256)) * 4,
            {},
            "file",
            r"^unknown format '\.bin': binary data",
        ),
        ("empty", "d.csv", b"", {}, "file", r"^the file is empty$"),
        (
            "field-sample-time",
            "d.csv",
            GOOD_CSV,
            {"sample_time": "fast"},
            "sample_time",
            r"^'fast' is not a number$",
        ),
        (
            "field-state-columns",
            "d.csv",
            GOOD_CSV,
            {"state_columns": "x1,pos"},
            "state_columns",
            r"^no column 'pos' in the file's header",
        ),
        (
            "field-state-columns-twice",
            "d.csv",
            GOOD_CSV,
            {"state_columns": "x1,x1"},
            "state_columns",
            r"^'x1' given twice$",
        ),
        (
            "field-input-columns-twice",
            "d.csv",
            GOOD_CSV,
            {"input_columns": "u1,u2,u1"},
            "input_columns",
            r"^'u1' given twice$",
        ),
        (
            "field-names-on-csv",
            "d.csv",
            GOOD_CSV,
            {"state_names": "a,b,c"},
            "state_names",
            r"^a CSV file names its channels by its columns",
        ),
        (
            "field-name-count",
            "d.npz",
            files.npz_bytes(X, U),
            {"state_names": "a,b"},
            "state_names",
            r"^2 names for 3 channels$",
        ),
        ("field-no-name", "d.csv", GOOD_CSV, {"name": ""}, "name", r"^is required$"),
        ("field-unknown", "d.csv", GOOD_CSV, {"colour": "red"}, "colour", r"^unknown field$"),
    ]
