"""Files of many short rollouts (docs/datasets.md#limits, docs/performance.md#while-parsed):
the rollouts are stacked in a few blocks, and read back as the arrays, statistics,
stored bytes and excitation check of the rollouts one by one, bit for bit; parsing
the worst legal CSV and JSON files takes a few times their numbers in memory, not a
few hundred bytes a rollout."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.db.datasets import array_chunks, arrays_digest
from svrobs_core.measured import MeasuredData, excitation
from svrobs_lab.datasets.catalog import upload_excitation
from svrobs_lab.datasets.csv_format import BLOCK_ROWS
from svrobs_lab.datasets.reader import parse_dataset
from tests.datasets import files

ROOT = Path(__file__).resolve().parents[2]


def parse(data: bytes, filename: str):
    return parse_dataset(io.BytesIO(data), filename=filename, max_bytes=64 * 2**20)


def folded_stats(arrays: list[np.ndarray], names: list[str]) -> dict:
    """The statistics as a fold over the rollouts one by one: each rollout's sum, min
    and max, then the squared deviations, rollout after rollout."""
    width = arrays[0].shape[1]
    if width == 0:
        return {}
    count = sum(len(a) for a in arrays)
    total, dev = np.zeros(width), np.zeros(width)
    lo, hi = np.full(width, np.inf), np.full(width, -np.inf)
    for a in arrays:
        total += a.sum(axis=0)
        lo, hi = np.minimum(lo, a.min(axis=0)), np.maximum(hi, a.max(axis=0))
    mean = total / count
    for a in arrays:
        dev += ((a - mean) ** 2).sum(axis=0)
    std = np.sqrt(dev / count)
    keys = ("mean", "std", "min", "max")
    return {
        name: {**{k: float(v[j]) for k, v in zip(keys, (mean, std, lo, hi))}, "count": count}
        for j, name in enumerate(names)
    }


def same_arrays(got, want: list[np.ndarray]) -> bool:
    return len(got) == len(want) and all(
        g.dtype == np.float64 and g.shape == w.shape and g.tobytes() == w.tobytes()
        for g, w in zip(got, want)
    )


@pytest.mark.parametrize("m", [2, 0])
def test_many_short_rollouts_read_back_as_the_rollouts_one_by_one(m):
    """12,000 rollouts of 1 to 4 steps, two longer than BLOCK_ROWS among them: every
    array, the statistics, the stored bytes and the excitation check are those of
    the rollouts' own arrays."""
    lengths = [1 + i % 4 for i in range(12_000)]
    lengths[3_000] = BLOCK_ROWS + 5
    lengths[9_000] = 2 * BLOCK_ROWS + 1
    X, U = files.rollouts(seed=5, lengths=lengths, m=m)
    for name, data in (
        ("d.csv", files.csv_bytes(X, U)),
        ("d.json", files.json_bytes(X, U)),
    ):
        p = parse(data, name)
        assert same_arrays(p.X, X) and same_arrays(p.U, U), name
        assert p.lengths == lengths and p.samples == sum(lengths)
        assert len(p.X.blocks) < len(lengths) / 50, name  # stacked, not an array a rollout
        want = {
            "states": folded_stats(X, p.state_names),
            "inputs": folded_stats(U, p.input_names),
        }
        assert json.dumps(p.stats) == json.dumps(want), name
        stored = b"".join(array_chunks(p.arrays(), size=1000))
        assert stored == b"".join(array_chunks(X + U, size=1000))
        assert arrays_digest(p.arrays()) == arrays_digest(X + U)
        assert upload_excitation(p) == excitation(MeasuredData(X=X, U=U)).to_dict(), name


def test_a_zero_extreme_has_the_sign_the_rollout_fold_gives_it():
    """0.0 and -0.0 are equal, so the min (max) of a column holding both is either,
    and numpy's min of a block of rollouts may keep another one than the fold over
    the rollouts: the statistics keep the fold's."""
    rng = np.random.default_rng(7)
    for _ in range(100):
        values = rng.choice([0.0, -0.0, 1.0, 2.0], size=int(rng.integers(20, 80)))
        cuts = np.sort(rng.choice(np.arange(1, len(values)), size=4, replace=False))
        for sign in (1.0, -1.0):
            U = [sign * u[:, None] for u in np.split(values, cuts)]
            X = [np.zeros((len(u) + 1, 1)) for u in U]
            got = parse(files.csv_bytes(X, U), "d.csv").stats["inputs"]["u1"]
            want = folded_stats(U, ["u1"])["u1"]
            for key in ("min", "max"):
                assert np.signbit(got[key]) == np.signbit(want[key]), (values.tolist(), cuts)


# the growth of the peak resident memory (VmHWM) over the parse, in a fresh process: its
# peak reset to what it holds first (ru_maxrss would start at the launching process's)
MEASURE = """
import io, json, re, sys
from svrobs_lab.datasets.reader import parse_dataset
def kb(key):
    return int(re.search(key + r":\\s+(\\d+) kB", open("/proc/self/status").read()).group(1))
path = sys.argv[1]
warm = b"rollout,k,x1\\n0,0,1\\n0,1,2\\n" if path.endswith(".csv") else b'{"X": [[[1], [2]]]}'
parse_dataset(io.BytesIO(warm), filename=path, max_bytes=2**20)
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")
before = kb("VmRSS")
with open(path, "rb") as f:
    parsed = parse_dataset(f, filename=path, max_bytes=2**28)
after = kb("VmHWM")
numbers = sum(x.size for x in parsed.X) + sum(u.size for u in parsed.U)
print(json.dumps({"growth": (after - before) * 1024, "data": 8 * numbers}))
"""


def _short_rollouts_csv(path: Path, rollouts: int) -> None:
    """Rollouts of 3 rows, n = m = 1: the most rollouts for the numbers."""
    rows = (
        f"{i},{k},{(i * 7 + k) % 1000 / 100},{'' if k == 2 else (i + k) % 10}"
        for i in range(rollouts)
        for k in range(3)
    )
    path.write_text("rollout,k,x1,u1\n" + "\n".join(rows) + "\n")


def _short_rollouts_json(path: Path, rollouts: int) -> None:
    """Rollouts of 2 states, n = 1, no inputs: 3 lists a rollout, under 2,000,000."""
    body = ",".join(f"[[{i % 1000 / 10}],[{(i * 3) % 100}]]" for i in range(rollouts))
    path.write_text('{"X": [' + body + "]}")


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="Linux's /proc")
@pytest.mark.parametrize(
    "name, write, rollouts",
    [("short.csv", _short_rollouts_csv, 300_000), ("short.json", _short_rollouts_json, 600_000)],
)
def test_parsing_many_rollouts_takes_a_few_times_their_numbers_in_memory(
    tmp_path, name, write, rollouts
):
    """The growth of the parsing process's peak memory (a fresh process; the file's
    text and arrays, 8 bytes a rollout for its place, and what converts a block at a
    time) is at most 5 times the float64 numbers: about 2x (CSV) and 3x (JSON) here,
    where an array a rollout (some 500 bytes a rollout) makes it 15x and 35x."""
    path = tmp_path / name
    write(path, rollouts)
    out = subprocess.run(
        [sys.executable, "-c", MEASURE, str(path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
        timeout=600,
    )
    got = json.loads(out.stdout)
    assert got["data"] > 8e6
    assert got["growth"] <= 5 * got["data"], (
        f"{name}: {got['growth'] / 2**20:.0f} MB for {got['data'] / 2**20:.1f} MB of numbers"
    )
