"""The compact storage of records (docs/spec.md#record-fields) in ``results``.

A job's rows are decoded with its spec (:class:`ResultCodec`): each matrix field
is stored as its entries, row-major little-endian float64, with no shape (the
shape follows from the system's n, m, p: A_hat and radii_A n x n, B_hat and
radii_B n x m, L and K n x p), or as 8 bytes when every entry is the same
float; a non-finite entry (the records' null) is read back as None. A matrix that is the same in every cell of a (system, sigma_w) of the
job (K, the true system's Kalman gain: docs/science.md#5-the-optimal-gain-k) is stored once in
``result_constants`` and as zero bytes in its rows; a radius matrix whose every
entry is its row's scalar radius (radii_A = r_A, radii_B = r_B: the paper's
bounds, docs/science.md#33-lemma-2-entrywise-intervals) is stored as zero bytes too (migration
0007). ``seed_key`` is stored
only when it differs from the one the spec gives a cell: ``[system index,
sigma_w index, N, rep]``. Reads decode a batch of rows at once (one
``numpy.frombuffer`` per field and system). A dataset job's shapes come from its
dataset's n and m (an n x 0 matrix, when there are no inputs, is zero bytes).
"""

from __future__ import annotations

import functools
import json
from collections.abc import Sequence
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import cast

import numpy as np

from svrobs_core import parse_spec, resolve_system
from svrobs_core.measured import data_layout
from svrobs_core.records import json_value

DTYPE = np.dtype("<f8")
_NONE = np.array(None)  # None as an array: what where() puts at the non-finite entries
SHARED_FIELDS = ("K",)  # matrices stored once per (job, system, sigma_w) when constant
SHARED = b""  # the stored value of a row whose matrix is its (system, sigma_w)'s constant
# a radius matrix stored as zero bytes: every entry is the row's scalar radius
RADIUS_SCALAR = {"radii_A": "r_A", "radii_B": "r_B"}


@dataclass(frozen=True)
class ResultCodec:
    """How one job's records are stored: matrix shapes and spec indices per system."""

    shapes: dict[str, dict[str, tuple[int, int]]]  # system name -> field -> (rows, cols)
    system_index: dict[str, int]
    sigma_index: dict[float, int]
    # (system, sigma_w, field) -> bytes: the job's rows in result_constants
    constants: dict[tuple[str, float, str], bytes] = dc_field(default_factory=dict)

    @classmethod
    def of(cls, spec: dict, data: tuple[int, int] | None = None) -> ResultCodec:
        """The codec of a job's (validated) spec dict; cached on its systems and
        sigma_w. A dataset job's needs ``data``, its dataset's (n, m): the shapes
        follow from them and the spec (:func:`svrobs_core.measured.data_layout`)."""
        if "dataset" in spec:
            if data is None:
                raise ValueError("a dataset job's codec needs the dataset's (n, m)")
            return _dataset_codec(json.dumps([spec, list(data)], sort_keys=True))
        return _codec(json.dumps([spec["systems"], spec["sigma_w"]], sort_keys=True))

    def shape(self, system: str, field: str) -> tuple[int, int]:
        try:
            return self.shapes[system][field]
        except KeyError:
            raise ValueError(f"system {system!r} is not in the job's spec") from None

    # -- matrices ---------------------------------------------------------------------
    def encode_matrix(self, system: str, field: str, value, scalar=None) -> bytes | None:
        """A record's matrix (nested lists, None entries allowed) -> bytes; None -> None.
        ``scalar``: the row's r_A / r_B for a radius matrix (see :meth:`encode_block`)."""
        if value is None:
            return None
        a = np.asarray(value, dtype=float)  # None -> nan
        if a.shape != self.shape(system, field):
            raise ValueError(
                f"{field} of system {system!r} must be {self.shape(system, field)}, got {a.shape}"
            )
        return self.encode_block(a[None], None if scalar is None else [scalar])[0]

    @staticmethod
    def encode_block(block: np.ndarray, scalars=None) -> list[bytes]:
        """(k, rows, cols) matrices -> k byte strings (vectorised); a matrix whose
        entries are all the same float (bit for bit) as that one float's 8 bytes, and
        as zero bytes when that float is also the row's finite ``scalars[i]`` (a radius
        matrix equal to its row's scalar radius; None entries of ``scalars`` never)."""
        a = np.ascontiguousarray(block, dtype=DTYPE)
        k = a.shape[0]
        if not k:
            return []
        if not a[0].size:  # matrices without entries (n x 0: no inputs)
            return [b""] * k
        flat = a.reshape(k, -1)
        # the items of an unstructured void array are bytes (numpy types them bytes or tuple)
        out = cast(
            "list[bytes]", flat.view(np.dtype((np.void, flat.shape[1] * 8))).ravel().tolist()
        )
        bits = flat.view(np.int64)
        uniform = (bits == bits[:, :1]).all(axis=1)
        if scalars is not None:
            sc = np.array([np.nan if v is None else v for v in scalars], dtype=DTYPE)
            same = uniform & np.isfinite(sc) & (sc.view(np.int64) == bits[:, 0])
            for i in np.flatnonzero(same).tolist():
                out[i] = b""
            uniform &= ~same
        for i in np.flatnonzero(uniform).tolist():
            out[i] = out[i][:8]
        return out

    def decode_matrices(
        self,
        systems: Sequence[str],
        sigmas: Sequence[float],
        field: str,
        blobs: Sequence,
        scalars: Sequence | None = None,
    ) -> list:
        """One matrix field of many rows -> nested lists (None where the row has none,
        None entries where a value is not finite). ``scalars``: the rows' r_A / r_B,
        needed for a radius field (its zero-byte rows are that scalar everywhere)."""
        out: list = [None] * len(blobs)
        by_system: dict[str, list[int]] = {}
        for i, (s, b) in enumerate(zip(systems, blobs)):
            if b is not None:
                by_system.setdefault(s, []).append(i)
        for system, idx in by_system.items():
            r, c = self.shape(system, field)
            if r * c == 0:  # n x 0 (no inputs: B_hat, radii_B), stored as zero bytes
                for i in idx:
                    out[i] = [[] for _ in range(r)]
                continue
            parts = [bytes(blobs[i]) for i in idx]
            if SHARED in parts and field in RADIUS_SCALAR:
                if scalars is None:
                    raise ValueError(f"{field} needs the rows' {RADIUS_SCALAR[field]} to decode")
                parts = [p or DTYPE.type(scalars[i]).tobytes() for p, i in zip(parts, idx)]
            elif SHARED in parts:
                parts = [p or self._constant(system, sigmas[i], field) for p, i in zip(parts, idx)]
            if r * c > 1:  # a matrix of one repeated float is stored as that float
                parts = [p * (r * c) if len(p) == 8 else p for p in parts]
            buf = b"".join(parts)
            if len(buf) != len(idx) * r * c * DTYPE.itemsize:
                raise ValueError(f"stored {field} of system {system!r} is not {r}x{c} float64")
            a = np.frombuffer(buf, dtype=DTYPE).reshape(len(idx), r, c)
            values = a.tolist()
            finite = np.isfinite(a)
            for j in np.flatnonzero(~finite.all(axis=(1, 2))).tolist():
                values[j] = np.where(finite[j], a[j], _NONE).tolist()
            for i, v in zip(idx, values):
                out[i] = v
        return out

    def _constant(self, system: str, sigma_w: float, field: str) -> bytes:
        try:
            return self.constants[(system, float(sigma_w), field)]
        except KeyError:
            raise ValueError(f"no stored {field} of ({system!r}, {sigma_w})") from None

    # -- seed_key ---------------------------------------------------------------------
    def derived_seed_key(self, system: str, sigma_w: float, N: int, rep: int) -> list | None:
        si, wi = self.system_index.get(system), self.sigma_index.get(float(sigma_w))
        return None if si is None or wi is None else [si, wi, int(N), int(rep)]

    def encode_seed_key(self, system: str, sigma_w: float, N: int, rep: int, value) -> str | None:
        """None when ``value`` is the derived key (stored as NULL), else its JSON text."""
        value = json_value(value)
        if isinstance(value, list) and value == self.derived_seed_key(system, sigma_w, N, rep):
            return None
        return json.dumps(value)

    def decode_seed_keys(self, systems, sigmas, Ns, reps, texts) -> list:
        return [
            self.derived_seed_key(s, w, n, r) if t is None else json.loads(t)
            for s, w, n, r, t in zip(systems, sigmas, Ns, reps, texts)
        ]


@functools.lru_cache(maxsize=256)
def _dataset_codec(key: str) -> ResultCodec:
    spec, (n, m) = json.loads(key)
    layout = data_layout(parse_spec(spec), n, m)
    return ResultCodec(
        shapes={layout.system: layout.matrix_shapes},
        system_index={layout.system: 0},
        sigma_index={float(layout.sigma_w): 0},
    )


@functools.lru_cache(maxsize=256)
def _codec(key: str) -> ResultCodec:
    systems_raw, sigmas = json.loads(key)
    systems = [resolve_system(s, field=f"systems[{i}]") for i, s in enumerate(systems_raw)]
    shapes = {
        s.name: {
            "A_hat": (s.n, s.n),
            "B_hat": (s.n, s.m),
            "radii_A": (s.n, s.n),
            "radii_B": (s.n, s.m),
            "L": (s.n, s.p),
            "K": (s.n, s.p),
        }
        for s in systems
    }
    return ResultCodec(
        shapes=shapes,
        system_index={s.name: i for i, s in enumerate(systems)},
        sigma_index={float(w): i for i, w in enumerate(sigmas)},
    )
