"""Memory and time of ``parse_dataset`` on the worst legal CSV and JSON files: the most
rollouts and lists the limits allow (docs/datasets.md#limits), each rollout as short
as allowed, so that whatever a rollout costs beside its numbers shows.

    .venv/bin/python bench/dataset_parse.py                  # every file, 3 runs each
    .venv/bin/python bench/dataset_parse.py --only csv3 --runs 1 --dir /tmp/parse-files

Each measurement is a fresh process (``--measure FILE``): it parses a small file of
the same format first (lazy imports), resets its peak resident memory to what it holds
(``/proc/self/clear_refs``), reads VmRSS, parses the file with ``parse_dataset`` timed
by ``time.perf_counter`` and reads VmHWM, the peak: the growth is the difference.
(``ru_maxrss`` is no measure here: in a process started by another it begins at the
starting process's peak.) The float64 data is 8 bytes per number of the arrays the
file holds. The files are written once into ``--dir`` (default: a temporary folder)
and kept there when it is given; ``--root`` measures the code of another checkout.
"""

from __future__ import annotations

import argparse
import io
import json
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

MB = 2**20

# the files: what each holds (written by write())
FILES = {
    "csv3": "CSV, 1,000,000 rollouts of 3 rows, n = m = 1",
    "csv2": "CSV, 1,000,000 rollouts of 2 rows, n = 1, m = 0",
    "json2": "JSON, 666,666 rollouts of 2 states, n = 1, m = 0",
    "json1": "JSON, 1 rollout of 1,999,990 states, n = 1, m = 0",
    "jsonu": "JSON, 399,999 rollouts of 2 states and 1 input, n = m = 1",
    # for comparison: few long rollouts, numbers of 17 digits (about 50 MB)
    "csvlong": "CSV, 209 rollouts of 2001 rows, n = 4, m = 2",
}


def _number(i: int) -> str:
    """A short number of up to 3 significant digits, signs and zeros mixed."""
    return ("-" if i % 7 == 3 else "") + f"{(i * 37) % 1000 / 100:g}"


def _csv(path: Path, rows: int, inputs: bool) -> int:
    header = "rollout,k,x1" + (",u1" if inputs else "")
    numbers = 0
    with path.open("w") as f:
        f.write(header + "\n")
        lines = []
        for i in range(1_000_000):
            for k in range(rows):
                u = ("," + (_number(i + k + 1) if k < rows - 1 else "")) if inputs else ""
                lines.append(f"{i},{k},{_number(i + k)}{u}\n")
            numbers += rows + (rows - 1 if inputs else 0)
            if len(lines) > 100_000:
                f.write("".join(lines))
                lines.clear()
        f.write("".join(lines))
    return numbers


def _json(path: Path, rollouts: int, states: int, inputs: bool) -> int:
    xs = (
        "[" + ",".join(f"[{_number(i + k)}]" for k in range(states)) + "]" for i in range(rollouts)
    )
    body = '{"X": [' + ",".join(xs) + "]"
    if inputs:
        us = (
            "[" + ",".join(f"[{_number(i + k + 1)}]" for k in range(states - 1)) + "]"
            for i in range(rollouts)
        )
        body += ', "U": [' + ",".join(us) + "]"
    path.write_text(body + "}")
    return rollouts * (states + (states - 1 if inputs else 0))


def _long_csv(path: Path, rollouts: int, steps: int, n: int, m: int) -> int:
    rng = np.random.default_rng(0)
    header = ["rollout", "k", *(f"x{j + 1}" for j in range(n)), *(f"u{j + 1}" for j in range(m))]
    with path.open("w") as f:
        f.write(",".join(header) + "\n")
        for i in range(rollouts):
            values = rng.standard_normal((steps + 1, n + m)).tolist()
            for k, row in enumerate(values):
                cells = [repr(v) for v in row[: n + (m if k < steps else 0)]]
                f.write(f"{i},{k}," + ",".join(cells + [""] * (m if k == steps else 0)) + "\n")
    return rollouts * ((steps + 1) * n + steps * m)


def write(name: str, path: Path) -> int:
    """Write the file ``name`` at ``path``; the numbers its arrays hold."""
    if name == "csvlong":
        return _long_csv(path, 209, 2000, 4, 2)
    if name == "csv3":
        return _csv(path, 3, True)
    if name == "csv2":
        return _csv(path, 2, False)
    if name == "json2":
        return _json(path, 666_666, 2, False)
    if name == "json1":
        return _json(path, 1, 1_999_990, False)
    return _json(path, 399_999, 2, True)


def _kb(key: str) -> int:
    """A line of /proc/self/status, in kB (VmRSS: resident now; VmHWM: the peak)."""
    return int(re.search(key + r":\s+(\d+) kB", Path("/proc/self/status").read_text()).group(1))


def measure(path: Path) -> dict:
    """In this (fresh) process: the growth of the peak resident memory over one parse,
    and its time."""
    from svrobs_lab.datasets.reader import parse_dataset

    small = (
        b"rollout,k,x1,u1\n0,0,1,2\n0,1,3,\n" if path.suffix == ".csv" else b'{"X": [[[1],[2]]]}'
    )
    parse_dataset(io.BytesIO(small), filename="s" + path.suffix, max_bytes=MB)
    Path("/proc/self/clear_refs").write_text("5")  # the peak: what the process holds now
    before = _kb("VmRSS")
    t0 = time.perf_counter()
    with path.open("rb") as f:
        parsed = parse_dataset(f, filename=path.name, max_bytes=256 * MB)
    seconds = time.perf_counter() - t0
    after = _kb("VmHWM")
    return {"growth_mb": (after - before) / 1024, "seconds": seconds, "rollouts": parsed.rollouts}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--measure", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--only", nargs="*", choices=sorted(FILES), default=sorted(FILES))
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--dir", type=Path)
    ap.add_argument("--root", type=Path, default=ROOT, help="the checkout whose code is measured")
    args = ap.parse_args()
    sys.path.insert(0, str(args.root))
    if args.measure:
        print(json.dumps(measure(args.measure)))
        return
    with tempfile.TemporaryDirectory(prefix="svrobs-parse-") as tmp:
        folder = args.dir or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for name in args.only:
            path = folder / f"{name}.{'csv' if name.startswith('csv') else 'json'}"
            counts = folder / f"{name}.numbers"
            if not (path.exists() and counts.exists()):
                counts.write_text(str(write(name, path)))
            data = int(counts.read_text()) * 8 / MB
            runs = []
            for _ in range(args.runs):
                out = subprocess.run(
                    [sys.executable, __file__, "--measure", str(path), "--root", str(args.root)],
                    check=True,
                    capture_output=True,
                    text=True,
                )
                runs.append(json.loads(out.stdout))
            growth = statistics.median(r["growth_mb"] for r in runs)
            seconds = statistics.median(r["seconds"] for r in runs)
            print(
                f"{name}: {FILES[name]}: file {path.stat().st_size / MB:.1f} MB, data "
                f"{data:.1f} MB; growth {growth:.0f} MB ({growth / data:.2f} x the data), "
                f"{seconds:.2f} s (median of {args.runs}; runs: "
                + ", ".join(f"{r['growth_mb']:.0f} MB {r['seconds']:.2f} s" for r in runs)
                + ")",
                flush=True,
            )


if __name__ == "__main__":
    main()
