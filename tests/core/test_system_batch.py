"""The checks of a spec's systems across systems (svrobs_core.system_batch, and the
system table and kinds of svrobs_core.workload) against the one-system functions
they stand for, on random systems (hypothesis), valid and broken in every way the
per-system checks refuse: the same systems to the last bit, or the same first
error naming the same field; the same kinds, costs and smallest units. The
messages are pinned word for word. Not timed: bench/many_systems.py."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from svrobs_core import SpecError, parse_spec, plan_units
from svrobs_core.admission import grid_cost, smallest_unit_bytes, smallest_unit_seconds
from svrobs_core.gains import is_orthogonal, orthogonal_each
from svrobs_core.system_batch import resolve_systems
from svrobs_core.systems import resolve_system
from svrobs_core.workload import (
    _dims,
    _fit,
    _ill_conditioned,
    estimate_job,
    estimate_unit,
    plan_under_memory,
    system_kinds,
    system_table,
)

# what can be wrong with a system object (None: nothing)
FLAWS = [
    None,
    None,
    None,
    "nan",
    "inf",
    "huge entry",
    "bool entry",
    "string entry",
    "int entries",
    "int beyond float",
    "numpy float",
    "ragged",
    "not square",
    "B rows",
    "B flat",
    "B empty",
    "deeper",
    "no C",
    "C columns",
    "C too tall",
    "sigma_u 0",
    "sigma_u string",
    "sigma_u bool",
    "sigma_u huge",
    "sigma_u null",
    "sigma_v negative",
    "sigma_v 0",
    "sigma_v 0 singular",
    "sigma_v 0 not square",
    "name empty",
    "name long",
    "name control",
    "name number",
    "unknown key",
    "no B",
    "preset",
    "unknown preset",
    "not an object",
    "A too large",
]


def _system(i: int, seed: int, flaw: str | None) -> object:
    """System ``i``: n, m, p of 1-3, A scaled to a spectral radius in [0.2, 1.6],
    with ``flaw``."""
    rng = np.random.default_rng(seed)
    n, m, p = (int(v) for v in rng.integers(1, 4, size=3))
    A = rng.standard_normal((n, n))
    A *= rng.uniform(0.2, 1.6) / max(np.max(np.abs(np.linalg.eigvals(A))), 1e-9)
    s: dict = {
        "name": f"s{i}",
        "A": A.tolist(),
        "B": rng.standard_normal((n, m)).tolist(),
        "C": rng.standard_normal((p, n)).tolist(),
    }
    if rng.random() < 0.3:
        s["sigma_u"] = float(rng.uniform(0.1, 3.0))
    if rng.random() < 0.3:
        s["sigma_v"] = float(rng.uniform(0.0, 1.0))
    if rng.random() < 0.2:  # an orthogonal or identity C
        s["C"] = np.eye(n)[rng.permutation(n)].tolist() if rng.random() < 0.5 else None
    if flaw is None:
        return s
    return _flawed(s, flaw, n, rng)


def _flawed(s: dict, flaw: str, n: int, rng: np.random.Generator) -> object:
    A = s["A"]
    special = {
        "preset": "paper-stable" if rng.random() < 0.5 else "paper-unstable",
        "unknown preset": "paper-wobbly",
        "not an object": [1, 2],
    }
    if flaw in special:
        return special[flaw]
    edits = {
        "nan": lambda: A[0].__setitem__(0, float("nan")),
        "inf": lambda: s["B"][0].__setitem__(0, float("-inf")),
        "huge entry": lambda: A[-1].__setitem__(-1, 2e100),
        "bool entry": lambda: s["B"][-1].__setitem__(0, True),
        "string entry": lambda: A[0].__setitem__(0, "0.5"),
        "int entries": lambda: s.update(A=[[int(v * 10) for v in row] for row in A]),
        "int beyond float": lambda: A[0].__setitem__(0, 10**400),
        "numpy float": lambda: A[0].__setitem__(0, np.float64(0.25)),
        "ragged": lambda: A[0].append(0.0),
        "not square": lambda: s.update(A=A + [[0.0] * n]),
        "B rows": lambda: s.update(B=s["B"] + [[1.0] * len(s["B"][0])]),
        "B flat": lambda: s.update(B=[row[0] for row in s["B"]]),
        "B empty": lambda: s.update(B=[]),
        "deeper": lambda: s.update(B=[[[v] for v in row] for row in s["B"]]),
        "no C": lambda: s.pop("C", None),
        "C columns": lambda: s.update(C=[[1.0] * (n + 1)]),
        "C too tall": lambda: s.update(C=[[1.0] * n] * 51),
        "sigma_u 0": lambda: s.update(sigma_u=0),
        "sigma_u string": lambda: s.update(sigma_u="1"),
        "sigma_u bool": lambda: s.update(sigma_u=True),
        "sigma_u huge": lambda: s.update(sigma_u=1e200),
        "sigma_u null": lambda: s.update(sigma_u=None),
        "sigma_v negative": lambda: s.update(sigma_v=-0.1),
        "sigma_v 0": lambda: s.update(sigma_v=0.0, C=np.eye(n)[::-1].tolist()),
        "sigma_v 0 singular": lambda: s.update(sigma_v=0, C=[[1.0] * n] * n),
        "sigma_v 0 not square": lambda: s.update(sigma_v=0.0, C=[[1.0] * n]),
        "name empty": lambda: s.update(name="  "),
        "name long": lambda: s.update(name="x" * 65),
        "name control": lambda: s.update(name="a\x1bb"),
        "name number": lambda: s.update(name=3),
        "unknown key": lambda: s.update(colour="red"),
        "no B": lambda: s.pop("B"),
        "A too large": lambda: s.update(A=np.eye(51).tolist(), B=[[1.0]] * 51, C=None),
    }
    edits[flaw]()
    return s


def _one_by_one(raw: list) -> tuple:
    return tuple(resolve_system(s, field=f"systems[{i}]") for i, s in enumerate(raw))


def _outcome(resolve, raw):
    try:
        return resolve(raw)
    except SpecError as exc:
        return ("SpecError", exc.field, exc.message)
    except Exception as exc:  # noqa: BLE001  (the same exception either way)
        return (type(exc).__name__, str(exc))


def _assert_same_systems(got: tuple, want: tuple) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert (g.name, g.sigma_u, g.sigma_v) == (w.name, w.sigma_u, w.sigma_v)
        assert type(g.sigma_u) is type(w.sigma_u) and type(g.sigma_v) is type(w.sigma_v)
        for key in "ABC":
            a, b = getattr(g, key), getattr(w, key)
            assert a.shape == b.shape and a.dtype == b.dtype, key
            assert a.tobytes() == b.tobytes(), key  # the same bits, -0.0 and all
            assert not a.flags.writeable and a.flags.c_contiguous == b.flags.c_contiguous


raw_systems = st.lists(
    st.tuples(st.integers(0, 2**32 - 1), st.sampled_from(FLAWS)), min_size=1, max_size=8
)


@settings(max_examples=300, deadline=None)
@given(raw_systems)
def test_the_systems_and_the_first_error_are_those_of_one_by_one(items):
    raw = [_system(i, seed, flaw) for i, (seed, flaw) in enumerate(items)]
    want = _outcome(_one_by_one, raw)
    got = _outcome(resolve_systems, raw)
    if isinstance(want, tuple) and want and isinstance(want[0], str):
        assert got == want
    else:
        _assert_same_systems(got, want)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 2**32 - 1), min_size=1, max_size=12), st.integers(2, 60))
def test_the_kinds_are_each_systems_dims_and_conditioning(seeds, T0):
    raw = [_system(i, seed, None) for i, seed in enumerate(seeds)]
    raw.append({"name": "marginal", "A": [[1.0, 0.0], [0.0, -1.0]], "B": [[1.0], [0.0]]})
    spec = parse_spec({"systems": raw, "sigma_w": [1.0], "N": [10, 20], "T0": T0})
    kinds = system_kinds(spec)
    for si in range(len(spec.systems)):
        assert kinds.kind(si) == (*_dims(spec, si), _ill_conditioned(spec, si))
    assert int(kinds.counts.sum()) == len(spec.systems)
    table = system_table(spec)
    rho = [float(np.max(np.abs(np.linalg.eigvals(s.A)))) for s in spec.systems]
    assert table.rho.tolist() == rho


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(0, 2**32 - 1), min_size=2, max_size=8), st.integers(2, 40))
def test_the_costs_are_those_of_each_system_alone(seeds, T0):
    raw = [_system(i, seed, None) for i, seed in enumerate(seeds)]
    spec = parse_spec(
        {
            "systems": raw,
            "sigma_w": [0.5, 1.0],
            "N": [10, 20, 40],
            "T0": T0,
            "reps": 3,
            "estimators": ["ols", "svr"],
        }
    )
    grid = grid_cost(spec, target_cells=12, max_cells=12)
    alone = [
        grid_cost(replace(spec, systems=(s,)), target_cells=12, max_cells=12) for s in spec.systems
    ]
    assert grid.per_system == tuple(g.per_system[0] for g in alone)
    assert grid.cpu_seconds == float(sum(grid.per_system))
    assert grid.n_units == sum(g.n_units for g in alone)
    assert grid.n_units == len(plan_units(spec, target_cells=12, max_cells=12))
    assert grid.peak_unit_bytes == max(g.peak_unit_bytes for g in alone)
    assert grid.max_unit_seconds == max(g.max_unit_seconds for g in alone)
    Ns = [max(spec.N)]
    each = [
        estimate_unit(spec, {"system": si, "sigma_w": 0, "N": Ns, "reps": [0, 1]})
        for si in range(len(spec.systems))
    ]  # the one-system path (_dims, _ill_conditioned)
    assert smallest_unit_bytes(spec) == max(u.peak_bytes for u in each)
    assert smallest_unit_seconds(spec) == max(u.cpu_seconds for u in each)
    units = plan_units(spec)
    job = estimate_job(spec, units)
    costs = [estimate_unit(spec, u) for u in units]
    assert job.cpu_seconds == float(sum(c.cpu_seconds for c in costs))
    assert job.peak_unit_bytes == max(c.peak_bytes for c in costs)
    cap = min(c.peak_bytes for c in costs)  # splits every larger unit
    split = plan_under_memory(spec, max_unit_bytes=cap, max_unit_seconds=None)
    assert split == [v for u in units for v in _fit(spec, u, cap, None)]  # memo by system


def test_orthogonal_each_is_is_orthogonal_of_each():
    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    C = np.stack([np.eye(3), Q, 2 * np.eye(3), np.eye(3)[::-1], Q + 1e-9])
    assert orthogonal_each(C).tolist() == [is_orthogonal(c) for c in C]
    assert orthogonal_each(np.ones((4, 1, 3))).tolist() == [False] * 4


def _valid(i: int) -> dict:
    return {"name": f"ok{i}", "A": [[0.5, 0.1], [0.0, 0.5]], "B": [[1.0], [0.0]]}


# the first error of a spec whose system 3 has the flaw (and system 4 another):
# the message word for word
MESSAGES = [
    (
        {"A": [[0.5, float("nan")], [0.0, 0.5]]},
        "systems[3].A: contains NaN or inf",
    ),
    (
        {"B": [[1e101], [0.0]]},
        "systems[3].B: has an entry larger than 1e+100 in magnitude",
    ),
    (
        {"A": [["0.5", 0.0], [0.0, 0.5]]},
        "systems[3].A: must be a matrix of numbers (a list of rows of numbers)",
    ),
    (
        {"A": [[10**400, 0.0], [0.0, 0.5]]},
        "systems[3].A: must be a matrix of numbers (a list of rows)",
    ),
    (
        {"A": [[0.5, 0.0], [0.0]]},
        "systems[3].A: must be a matrix of numbers (a list of rows)",
    ),
    (
        {"A": [[]]},
        "systems[3].A: must be a non-empty matrix (a list of equal-length rows)",
    ),
    (
        {"A": [[0.5, 0.0]]},
        "systems[3].A: must be square, got 1x2",
    ),
    (
        {"B": [[1.0]]},
        "systems[3].B: must have 2 rows (as many as A), got 1",
    ),
    (
        {"C": [[1.0, 0.0, 0.0]]},
        "systems[3].C: must have 2 columns (as many as A), got 3",
    ),
    (
        {"C": [[1.0, 0.0]] * 51},
        "systems[3].C: is 51x2: at most 50 per side",
    ),
    (
        {"sigma_u": 0},
        "systems[3].sigma_u: must be > 0",
    ),
    (
        {"sigma_u": True},
        "systems[3].sigma_u: must be a number",
    ),
    (
        {"sigma_v": float("inf")},
        "systems[3].sigma_v: must be finite",
    ),
    (
        {"sigma_v": 1e101},
        "systems[3].sigma_v: must be at most 1e+100",
    ),
    (
        {"sigma_v": -1},
        "systems[3].sigma_v: must be >= 0",
    ),
    (
        {"sigma_v": 0, "C": [[1.0, 0.0], [1.0, 1e-13]]},
        "systems[3].sigma_v: sigma_v = 0 needs a square invertible C with cond(C) <= 1e+12"
        " (docs/science.md#5-the-optimal-gain-k)",
    ),
    (
        {"sigma_v": 0, "C": [[1.0, 0.0]]},
        "systems[3].sigma_v: sigma_v = 0 needs a square invertible C with cond(C) <= 1e+12"
        " (docs/science.md#5-the-optimal-gain-k)",
    ),
    (
        {"name": "a\nb"},
        "systems[3].name: must be a non-empty string of at most 64 printable characters"
        " (no control characters)",
    ),
    (
        {"colour": "red"},
        "systems[3].colour: unknown field",
    ),
]


@pytest.mark.parametrize("flaw, message", MESSAGES, ids=[m.split(":")[0] for _, m in MESSAGES])
def test_the_first_error_is_the_first_bad_systems_and_its_message_unchanged(flaw, message):
    systems = [_valid(i) for i in range(6)]
    systems[3] = {**systems[3], **flaw}
    systems[4] = {**systems[4], "A": [[10**400]]}  # a later error, in a later check
    systems[5] = "paper-stable"
    with pytest.raises(SpecError) as exc:
        parse_spec({"systems": systems, "sigma_w": [1.0], "N": [10]})
    assert str(exc.value) == message
    with pytest.raises(SpecError) as alone:
        _one_by_one(systems)
    assert str(alone.value) == message


def test_a_spec_of_many_shapes_is_the_one_by_one_spec():
    raw = [_system(i, i, None) for i in range(200)] + ["paper-unstable"]
    raw[17]["B"] = [row[0] for row in raw[17]["B"]]  # a flat column
    got = parse_spec({"systems": raw, "sigma_w": [1.0], "N": [10]}).systems
    _assert_same_systems(got, _one_by_one(raw))
