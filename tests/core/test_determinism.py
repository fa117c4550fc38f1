"""Every field, J_opt included, is bit-identical however the grid is split and
whichever process runs it (docs/science.md#14-randomness-and-reproducibility).

cvxpy's first solve of a freshly compiled SLS program gave J_opt in other last
bits than later solves, so a cell's J_opt depended on the cells solved before
it in its process. Each run here is a fresh interpreter, as a worker is.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np

from svrobs_core import sls

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SPEC = {
    "systems": [
        {
            "name": "custom-2x1",
            "A": [[0.9, 0.2], [0.0, 0.7]],
            "B": [[0.0], [1.0]],
            "C": [[1.0, 0.0]],
            "sigma_v": 0.5,
        },
        "paper-stable",
    ],
    "sigma_w": [1.0],
    "estimators": ["ols", "svr"],
    "reps": 2,
    "stages": ["estimate", "bounds", "gain", "cost", "cost_bound", "sls"],
    "mc_runs": 20,
    "horizon": 20,
    "sls": {"T_fir": 30},
}

_CHILD = """
import json, sys
from svrobs_core import parse_spec, run_spec
spec = parse_spec(json.loads(sys.argv[1]))
print(json.dumps([r for b in run_spec(spec) for r in b if r["N"] == 20], allow_nan=False))
"""


def _records_in_fresh_process(N: list[int]) -> list[dict]:
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, json.dumps({**SPEC, "N": N})],
        capture_output=True,
        text=True,
        check=True,
        env=env,
        timeout=300,
    )
    return json.loads(out.stdout)


def test_records_of_a_cell_do_not_depend_on_the_other_cells_of_the_grid():
    alone = _records_in_fresh_process([20])
    with_more = _records_in_fresh_process([10, 20])
    assert len(alone) == len(with_more) == 2 * 2 * 2
    assert all(r["J_opt"] is not None for r in alone)
    assert alone == with_more  # every field, J_opt to the last bit


def test_j_opt_does_not_depend_on_earlier_solves_in_the_process():
    rng = np.random.default_rng(1)
    A = np.array([[0.9, 0.2], [0.0, 0.7]])
    C, K = np.array([[1.0, 0.0]]), np.array([[0.5], [0.1]])
    for t in range(6):
        X, Y = (A + 0.05 * rng.standard_normal(A.shape) for _ in range(2))
        F, C_bound = float(rng.uniform(0, 30)), [None, 10.0][t % 2]
        sls.clear_cache()
        first = sls.sls_observer(X, C, K, F, C_bound=C_bound, T_fir=30).J_opt
        sls.clear_cache()
        sls.sls_observer(Y, C, K, F, C_bound=C_bound, T_fir=30)
        later = sls.sls_observer(X, C, K, F, C_bound=C_bound, T_fir=30).J_opt
        assert repr(first) == repr(later)
