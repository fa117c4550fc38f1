"""The dataset readers (svrobs_lab.datasets): one dataset written by independent writers
(csv, numpy.savez, scipy.io.savemat, hdf5storage) in every format reads back as the
same float64 arrays, bit for bit; the statistics equal numpy's over the stacked
samples; the conventions of each format (MATLAB's dropped singleton dimensions, CSV
column mapping, m = 0, ragged rollouts) hold."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from service.db.datasets import array_chunks, arrays_digest
from svrobs_core.errors import SpecError
from svrobs_lab.datasets.csv_format import BLOCK_ROWS
from svrobs_lab.datasets.parsed import DatasetOptions
from svrobs_lab.datasets.reader import parse_dataset
from svrobs_lab.errors import BadDatasetFile
from tests.datasets import files

LIMIT = 64 * 2**20
EXAMPLES = Path(__file__).resolve().parents[2] / "docs" / "examples"


def parse(data: bytes, filename: str = "", **options):
    return parse_dataset(
        io.BytesIO(data), filename=filename, options=DatasetOptions(**options), max_bytes=LIMIT
    )


def same_bits(got: list[np.ndarray], want: list[np.ndarray]) -> bool:
    return len(got) == len(want) and all(
        g.dtype == np.float64 and g.shape == w.shape and g.tobytes() == w.tobytes()
        for g, w in zip(got, want)
    )


@pytest.mark.parametrize("m", [2, 0])
def test_every_format_reads_the_same_arrays_bit_for_bit(tmp_path, m):
    X, U = files.rollouts(lengths=(7, 4, 5), m=m)
    digests = set()
    for fmt, (name, data) in files.all_formats(X, U, tmp_path).items():
        p = parse(data, name)
        assert p.format == fmt
        assert same_bits(p.X, X) and same_bits(p.U, U), fmt
        assert (p.n, p.m, p.rollouts, p.lengths) == (3, m, 3, [7, 4, 5])
        assert p.state_names == ["x1", "x2", "x3"] and p.input_names == [
            f"u{i + 1}" for i in range(m)
        ]
        digests.add(arrays_digest(p.X + p.U))
    assert len(digests) == 1


def test_equal_lengths_as_3d_arrays(tmp_path):
    X, U = files.rollouts(lengths=(5, 5, 5, 5))
    p = parse(files.npz_bytes(X, U, ragged=False))
    assert same_bits(p.X, X) and same_bits(p.U, U)
    import hdf5storage
    import scipy.io

    buf = io.BytesIO()
    scipy.io.savemat(buf, {"X": np.array(X), "U": np.array(U)})
    assert same_bits(parse(buf.getvalue()).U, U)
    path = tmp_path / "e.mat"
    hdf5storage.savemat(str(path), {"X": np.array(X), "U": np.array(U)}, format="7.3")
    p = parse(path.read_bytes())
    assert p.format == "mat73" and same_bits(p.X, X) and same_bits(p.U, U)


def test_matlab_drops_trailing_singletons_so_2d_means_one_channel():
    """A MATLAB N x (T+1) x 1 array is saved as N x (T+1): n = 1 (and m = 1 for U)."""
    import scipy.io

    X, U = files.rollouts(lengths=(4, 4), n=1, m=1)
    buf = io.BytesIO()
    scipy.io.savemat(buf, {"X": np.array(X)[:, :, 0], "U": np.array(U)[:, :, 0]})
    p = parse(buf.getvalue())
    assert (p.n, p.m) == (1, 1) and same_bits(p.X, X) and same_bits(p.U, U)
    # the same 2-D array in an NPZ is a shape error (no MATLAB convention there)
    with pytest.raises(
        BadDatasetFile, match=r"X: expected 3 dimensions \(rollouts, T\+1, n\), got 2"
    ):
        parse(files.npz_bytes(np.array(X)[:, :, 0], U, ragged=False))


def test_statistics_equal_numpy_over_the_stacked_samples():
    X, U = files.rollouts(lengths=(30, 1, 12))
    p = parse(files.csv_bytes(X, U))
    for arrays, stats, names in (
        (X, p.stats["states"], p.state_names),
        (U, p.stats["inputs"], p.input_names),
    ):
        stacked = np.vstack(arrays)
        for j, name in enumerate(names):
            s = stats[name]
            assert s["count"] == len(stacked)
            assert s["mean"] == pytest.approx(stacked[:, j].mean(), rel=1e-14, abs=1e-15)
            assert s["std"] == pytest.approx(stacked[:, j].std(), rel=1e-13)
            assert (s["min"], s["max"]) == (stacked[:, j].min(), stacked[:, j].max())


@pytest.mark.parametrize("scale", [1e307, 1e-308, 3e-310])
def test_statistics_of_finite_data_near_the_ends_of_the_double_range(scale):
    """Values whose sum overflows (1e307 x 40) or whose squares underflow (1e-308,
    subnormal 3e-310): the mean and std of the exact rationals (Fraction; the std as
    the square root of the exact variance), never null and never a std of 0."""
    from fractions import Fraction

    rng = np.random.default_rng(5)
    X = [(rng.uniform(1, 17, size=(40, 1)) * scale)]
    U = [np.ones((39, 1))]
    p = parse(files.npz_bytes(X, U))
    s = p.stats["states"][p.state_names[0]]
    exact = [Fraction(v) for v in X[0][:, 0].tolist()]
    mean = sum(exact) / len(exact)
    var = sum((v - mean) ** 2 for v in exact) / len(exact)
    assert s["mean"] == pytest.approx(float(mean), rel=1e-13, abs=0)
    want_std = float(var / Fraction(scale) ** 2) ** 0.5 * scale
    assert s["std"] == pytest.approx(want_std, rel=1e-12, abs=0)


def test_csv_column_mapping_delimiters_labels_and_long_rollouts():
    X, U = files.rollouts(lengths=(BLOCK_ROWS * 2 + 17, 3), n=2, m=1)
    data = files.csv_bytes(
        X, U, states=["pos", "vel"], inputs=["force"], labels=["run A", "run B"], extra=["note"]
    )
    p = parse(data, state_columns=("pos", "vel"), input_columns=("force",))
    assert same_bits(p.X, X) and same_bits(p.U, U)
    assert p.state_names == ["pos", "vel"] and p.input_names == ["force"]
    # semicolons, CRLF, a BOM, quoted labels and k starting at 5
    rows = []
    for i, line in enumerate(data.decode().splitlines()):
        cells = line.split(",")
        if i:
            cells[0], cells[1] = f'"{cells[0]}"', str(int(cells[1]) + 5)
        rows.append(";".join(cells))
    semi = ("\ufeff" + "\r\n".join(rows) + "\r\n").encode()
    q = parse(semi, state_columns=("pos", "vel"), input_columns=("force",))
    assert same_bits(q.X, X) and same_bits(q.U, U)
    # an explicitly empty input list: m = 0
    r = parse(data, state_columns=("pos", "vel"), input_columns=())
    assert r.m == 0 and same_bits(r.X, X)


@pytest.mark.parametrize("field", ["state_columns", "input_columns"])
def test_a_column_chosen_twice_is_an_error_on_the_field_not_the_file(field):
    X, U = files.rollouts(lengths=(3, 3), n=2, m=2)
    columns = {"state_columns": ("x1", "x2"), "input_columns": ("u1", "u2")}
    columns[field] = (*columns[field], columns[field][0])
    with pytest.raises(SpecError) as err:
        parse(files.csv_bytes(X, U), **columns)
    assert (err.value.field, err.value.message) == (field, f"{columns[field][0]!r} given twice")


@pytest.mark.parametrize(
    ("fmt", "X", "message"),
    [
        ("mat", np.empty((0,), dtype=object), r"X: an empty cell array \(no rollouts\)"),
        ("mat73", np.empty((0,), dtype=object), r"X: an empty cell array \(no rollouts\)"),
        ("mat", np.empty((0, 0)), "no rollouts"),
        ("mat73", np.empty((0, 0)), "no rollouts"),
        ("npz", np.empty((0, 0, 0)), "no rollouts"),
        ("mat", np.empty((3, 0)), "X: 0 states per rollout; a rollout needs at least 2 states"),
    ],
)
def test_an_empty_x_is_a_bad_file_saying_so(tmp_path, fmt, X, message):
    """An X without rollouts (an empty cell or matrix) or without states is named as
    such, not as a U shape the file does not hold."""
    import hdf5storage
    import scipy.io

    buf = io.BytesIO()
    if fmt == "npz":
        np.savez(buf, X=X)
    elif fmt == "mat":
        scipy.io.savemat(buf, {"X": X})
    else:
        path = tmp_path / "e.mat"
        hdf5storage.savemat(str(path), {"X": X}, format="7.3", matlab_compatible=True)
        buf.write(path.read_bytes())
    with pytest.raises(BadDatasetFile, match=f"^file: {message}$"):
        parse(buf.getvalue())


def test_names_and_sample_time_from_the_file_or_the_upload(tmp_path):
    X, U = files.rollouts(lengths=(3, 3), n=2, m=1)
    meta = {"sample_time": 0.05, "state_names": ["a", "b"], "input_names": ["c"]}
    for data in (
        files.json_bytes(X, U, **meta),
        files.npz_bytes(
            X, U, sample_time=0.05, state_names=np.array(["a", "b"]), input_names=np.array(["c"])
        ),
        files.mat5_bytes(
            X,
            U,
            sample_time=0.05,
            state_names=np.array(["a", "b"], dtype=object),
            input_names=np.array(["c"], dtype=object),
        ),
        files.mat73_bytes(
            X,
            U,
            tmp_path,
            sample_time=0.05,
            state_names=np.array(["a", "b"], dtype=object),
            input_names=np.array(["c"], dtype=object),
        ),
    ):
        p = parse(data)
        assert (p.sample_time, p.state_names, p.input_names) == (0.05, ["a", "b"], ["c"])
        q = parse(data, state_names=("p", "v"), sample_time=0.1)
        assert (q.sample_time, q.state_names, q.input_names) == (0.1, ["p", "v"], ["c"])


def test_the_stored_array_encoding_is_every_x_then_every_u_little_endian():
    X, U = files.rollouts(lengths=(2, 3))
    stored = b"".join(array_chunks(X + U, size=7))  # chunk edges inside numbers
    want = b"".join(a.astype("<f8").tobytes() for a in X + U)
    assert stored == want and all(len(c) == 7 for c in list(array_chunks(X + U, size=7))[:-1])


def test_the_committed_examples_hold_the_same_dataset():
    """docs/examples (written by docs/examples/make_examples.py, its v7.3 file by
    h5py in MATLAB's layout) read back as one dataset."""
    found = sorted(EXAMPLES.glob("rollouts.*")) + sorted(EXAMPLES.glob("rollouts_*.mat"))
    assert {p.name for p in found} >= {
        "rollouts.csv",
        "rollouts.npz",
        "rollouts.json",
        "rollouts_v5.mat",
        "rollouts_v73.mat",
    }
    parsed = {p.name: parse(p.read_bytes(), p.name) for p in found}
    ref = parsed["rollouts.csv"]
    assert ref.rollouts >= 2 and len(set(ref.lengths)) > 1  # ragged
    for name, p in parsed.items():
        assert same_bits(p.X, ref.X) and same_bits(p.U, ref.U), name
    assert {p.format for p in parsed.values()} == {"csv", "npz", "json", "mat", "mat73"}


def test_an_npz_is_refused_when_its_arrays_as_float64_exceed_the_budget():
    """The budget (4 x the upload limit) counts each array as it is read, float64, not
    as stored: 1 MB of int8 is 8 MB once read, over a 4 MB budget."""
    buf = io.BytesIO()
    np.savez(buf, X=np.zeros((1, 2**20, 1), dtype=np.int8))
    with pytest.raises(
        BadDatasetFile, match=r"^file: the arrays take 8 MB once read; at most 4 MB$"
    ):
        parse_dataset(io.BytesIO(buf.getvalue()), max_bytes=2**20)


@pytest.mark.parametrize("error", [MemoryError, RuntimeError, NotImplementedError])
def test_an_npz_array_that_cannot_be_read_is_a_bad_file_naming_it(monkeypatch, error):
    def failing(*args, **kwargs):
        raise error("cannot read")

    monkeypatch.setattr(np.lib.format, "read_array", failing)
    data = files.npz_bytes(*files.rollouts(lengths=(3, 3)), ragged=False)
    with pytest.raises(BadDatasetFile, match=r"^file: X: not a readable \.npy array: cannot read$"):
        parse(data)


def test_json_lists_are_counted_before_the_file_is_parsed(monkeypatch):
    """At MAX_JSON_LISTS lists (rows and rollouts) a JSON file is read, one more is
    refused before json.loads builds any of them (docs/datasets.md#limits; the limit
    lowered here to 1,000, the bad-file catalog has a file past the real one)."""
    from svrobs_lab.datasets import json_format

    monkeypatch.setattr(json_format, "MAX_JSON_LISTS", 1_000)
    MAX_JSON_LISTS = json_format.MAX_JSON_LISTS
    rows = MAX_JSON_LISTS - 2  # the X list and its one rollout
    body = ('{"X": [[' + ",".join(["[1]"] * rows) + "]]}").encode()
    parsed = parse_dataset(io.BytesIO(body), filename="d.json", max_bytes=len(body))
    assert parsed.lengths == [rows - 1] and parsed.n == 1 and parsed.m == 0
    more = body.replace(b"[[[1]", b"[[[1],[1]", 1)
    with pytest.raises(BadDatasetFile, match=f"at most {MAX_JSON_LISTS:,} lists"):
        parse_dataset(io.BytesIO(more), filename="d.json", max_bytes=len(more))
