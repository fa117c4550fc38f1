"""The radius matrices' short forms (``service.db.result_codec``, migration 0007): a
matrix whose every entry is bit for bit its row's finite scalar radius is stored as
zero bytes, one whose entries are all one other float as that float's 8 bytes, any
other in full; each decodes to the very matrix written (float64 bits compared)."""

from __future__ import annotations

import numpy as np
import pytest

from service.db.result_codec import ResultCodec

CODEC = ResultCodec.of({"systems": ["paper-stable"], "sigma_w": [1.0]})
N = 3  # paper-stable: radii_A is 3 x 3


def _bits(m) -> list:
    """float64 bit patterns; a decoded None entry (not finite) as NaN's."""
    a = np.asarray(m, dtype=object)
    return np.where(a == None, np.nan, a).astype("<f8").view(np.int64).tolist()  # noqa: E711


CASES = [  # (matrix entries, the row's r_A, stored length)
    (np.full((N, N), 0.125), 0.125, 0),  # the paper's bounds: zero bytes
    (np.full((N, N), 0.125), 0.25, 8),  # uniform, another float: one float
    (np.full((N, N), 0.0), -0.0, 8),  # -0.0 is not 0.0 bit for bit
    (np.full((N, N), np.inf), np.inf, 8),  # a scalar that is not finite: never zero bytes
    (np.full((N, N), 0.125), None, 8),  # no scalar radius
    (np.arange(9.0).reshape(N, N) / 7, 1 / 7, 72),  # a per-entry radius: in full
]


@pytest.mark.parametrize("matrix, r, length", CASES)
def test_radius_short_forms_round_trip(matrix, r, length):
    blobs = CODEC.encode_block(matrix[None], [r])
    assert len(blobs[0]) == length
    assert CODEC.encode_matrix("paper-stable", "radii_A", matrix.tolist(), r) == blobs[0]
    (back,) = CODEC.decode_matrices(["paper-stable"], [1.0], "radii_A", blobs, [r])
    assert _bits(back) == _bits(np.where(np.isfinite(matrix), matrix, np.nan))


def test_a_block_mixes_the_forms_row_by_row():
    rs = [0.5, 0.5, None, 2.0]
    block = np.stack([np.full((N, N), 0.5), np.eye(N), np.full((N, N), 0.5), np.full((N, N), 2.0)])
    blobs = CODEC.encode_block(block, rs)
    assert [len(b) for b in blobs] == [0, 72, 8, 0]
    back = CODEC.decode_matrices(["paper-stable"] * 4, [1.0] * 4, "radii_A", blobs, rs)
    assert _bits(back) == _bits(block)


def test_zero_bytes_of_a_radius_need_the_scalars():
    blobs = CODEC.encode_block(np.full((1, N, N), 0.5), [0.5])
    with pytest.raises(ValueError, match="r_A"):
        CODEC.decode_matrices(["paper-stable"], [1.0], "radii_A", blobs)
