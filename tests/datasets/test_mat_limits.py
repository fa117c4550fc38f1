"""MATLAB files that would read data from elsewhere on the server or inflate far
beyond their size are refused before anything is read: data kept outside the file
or behind a link, oversized text, a cell that is not one, a reference array or a
compressed cell whose contents pass the budget (docs/datasets.md#matlab)."""

from __future__ import annotations

import io

import h5py
import numpy as np
import pytest
import scipy.io

from svrobs_lab.datasets.mat_format import mat5_variables, mat73_variables
from svrobs_lab.datasets.parsed import BadDatasetFile

LIMIT = 100_000  # bytes of arrays once read


def _h5(tmp_path, build) -> io.BytesIO:
    path = tmp_path / "d.mat"
    with h5py.File(path, "w") as f:
        build(f)
    return io.BytesIO(path.read_bytes())


def _refused(stream, match: str, read=mat73_variables) -> None:
    with pytest.raises(BadDatasetFile, match=match):
        read(stream, max_array_bytes=LIMIT)


def test_data_stored_in_another_file_of_the_server_are_not_read(tmp_path):
    secret = tmp_path / "secret"
    secret.write_bytes(bytes(range(64)))

    def build(f):
        f.create_dataset("X", shape=(1, 64, 1), dtype="u1", external=[(str(secret), 0, 64)])

    _refused(_h5(tmp_path, build), r"X: data kept outside the file")


def test_a_virtual_dataset_over_another_file_is_not_read(tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as g:
        g["data"] = np.arange(8.0)

    def build(f):
        layout = h5py.VirtualLayout(shape=(8,), dtype="f8")
        layout[:] = h5py.VirtualSource(str(other), "data", shape=(8,))
        f.create_virtual_dataset("X", layout)

    _refused(_h5(tmp_path, build), r"X: data kept outside the file")


@pytest.mark.parametrize("link", ["external", "soft"])
def test_a_name_that_links_elsewhere_is_not_followed(tmp_path, link):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as g:
        g["X"] = np.zeros((1, 3, 1))

    def build(f):
        f["data"] = np.zeros((1, 3, 1))
        f["X"] = (
            h5py.ExternalLink(str(other), "/X") if link == "external" else h5py.SoftLink("/data")
        )

    _refused(_h5(tmp_path, build), r"X: a link to another file")


def test_text_is_counted_by_its_width_before_it_is_read(tmp_path):
    def build(f):
        f.create_dataset("state_names", data=np.array([b"a" * 400_000]), compression="gzip")

    _refused(_h5(tmp_path, build), r"the arrays take more than")


def test_numbers_marked_as_a_cell_are_not_read_as_references(tmp_path):
    def build(f):
        d = f.create_dataset("X", data=np.zeros(10))
        d.attrs["MATLAB_class"] = np.bytes_(b"cell")

    _refused(_h5(tmp_path, build), r"X: a cell array that holds no cells")


def test_a_reference_array_counts_in_the_budget(tmp_path):
    def build(f):
        f["a"] = np.zeros(1)
        refs = np.full(20_000, f["a"].ref, dtype=h5py.ref_dtype)
        d = f.create_dataset("X", data=refs, compression="gzip")
        d.attrs["MATLAB_class"] = np.bytes_(b"cell")

    _refused(_h5(tmp_path, build), r"the arrays take more than")


def _mat5(variables: dict, *, compress: bool = True) -> io.BytesIO:
    buf = io.BytesIO()
    scipy.io.savemat(buf, variables, do_compression=compress)
    return io.BytesIO(buf.getvalue())


@pytest.mark.parametrize("compress", [True, False])
def test_a_v5_cell_is_counted_by_its_contents(compress):
    cell = np.empty((1, 1), dtype=object)
    cell[0, 0] = np.zeros((200_000, 2))
    stream = _mat5({"X": cell}, compress=compress)
    if compress:
        assert len(stream.getvalue()) < 10_000  # 3.2 MB of zeros in a few kB
    _refused(stream, r"the arrays take more than", read=mat5_variables)


def test_v5_text_is_counted():
    _refused(_mat5({"state_names": "a" * 200_000}), r"the arrays take more than", mat5_variables)


def test_a_v5_cell_within_the_budget_is_read():
    cell = np.empty((1, 2), dtype=object)
    cell[0, 0], cell[0, 1] = np.ones((4, 3)), np.ones((6, 3))
    out = mat5_variables(_mat5({"X": cell}), max_array_bytes=LIMIT)
    assert [x.shape for x in out["X"]] == [(4, 3), (6, 3)]
