"""Pins the records of a fixed multi-system spec with every stage: a change of
structure must not change a bit, and a change that alters records on purpose
updates the hash and says why in its commit.

OpenBLAS picks its kernels by CPU (``SkylakeX`` on AVX-512 hosts, ``Haswell``/``Zen``
on AVX2 ones), and the kernels round the last bits differently, so the hashes are
taken in a child process with ``OPENBLAS_CORETYPE=Haswell``: the same kernels, and so
the same bits, on every x86-64 host with AVX2.

``FINGERPRINT_V1`` hashes the records restricted to ``FIELDS_V1`` (every field
but bounds_method, radii_A and radii_B, in their order), so a change that only
adds record fields leaves it as it is; ``FINGERPRINT`` pins the full records."""

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from svrobs_core import parse_spec, run_spec

SPEC = {
    "systems": [
        "paper-stable",
        "paper-unstable",
        {
            "name": "custom-2x1",
            "A": [[0.9, 0.2], [0.0, 0.7]],
            "B": [[0.0], [1.0]],
            "C": [[1.0, 0.0]],
            "sigma_u": 1.0,
            "sigma_v": 0.5,
        },
    ],
    "sigma_w": [0.1, 1.0],
    "N": [8, 20],
    "gamma": [0.01, 0.1],
    "estimators": ["ols", "svr", "shrunk-ols"],
    "reps": 2,
    "stages": ["estimate", "bounds", "gain", "cost", "cost_bound", "sls"],
    "mc_runs": 50,
    "mc_reps": 1,
    "horizon": 30,
    "sls": {"T_fir": 10},
    "seed": 123,
}

# sha256 of the records (one JSON line each, keys in contract order) restricted
# to FIELDS_V1; the commit that changes it says which fields changed and by how much.
# (Under OpenBLAS's SkylakeX kernels the same records hash to c1b6b4e7... and
# bd1932b0...: the values differ in their last bits only.)
FINGERPRINT_V1 = "8741e30d16b7468d0ef9631b71956a86ee816fd2c3c57847da1863d8e3f5fa1b"
# sha256 of the full records.
FINGERPRINT = "15dde987d666e0df4353cb76373508de8c606728210a5f0d833d820bf2138ba3"

# The record fields but bounds_method, radii_A, radii_B, in contract order.
FIELDS_V1 = (
    "system sigma_w N N0 estimator gamma rep seed_key A_hat B_hat rmse_A rmse_B "
    "H_A H_B r_A r_B eps_A eps_B coverage_A coverage_B thm1_holds_A thm1_holds_B "
    "rho_upper_bound stable_certified L g_L certified rho_true K "
    "J_exact J_stationary J_mc J_mc_se J_star cost_ratio J_bound delta_J "
    "J_opt J_opt_bound sls_status notes"
).split()


def fingerprints(spec_obj) -> tuple[str, str]:
    """(sha256 of the full records, sha256 of the records restricted to FIELDS_V1)."""
    spec = parse_spec(spec_obj)
    full, v1 = hashlib.sha256(), hashlib.sha256()
    n = 0
    for batch in run_spec(spec):
        for r in batch:
            full.update(json.dumps(r, allow_nan=False).encode() + b"\n")
            old = {f: r[f] for f in FIELDS_V1}
            v1.update(json.dumps(old, allow_nan=False).encode() + b"\n")
            n += 1
    assert n == spec.n_cells
    return full.hexdigest(), v1.hexdigest()


def _has_avx2() -> bool:
    try:
        return " avx2" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


@pytest.mark.skipif(
    not _has_avx2(), reason="the pinned hashes are those of OpenBLAS's AVX2 kernels"
)
def test_records_fingerprint_is_unchanged():
    code = "from tests.core.test_fingerprint import SPEC, fingerprints; print(*fingerprints(SPEC))"
    env = {**os.environ, "OPENBLAS_CORETYPE": "Haswell"}
    root = Path(__file__).resolve().parents[2]
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=root, capture_output=True, text=True, check=True
    )
    full, v1 = out.stdout.split()
    assert v1 == FINGERPRINT_V1  # no value of a pre-existing field changed
    assert full == FINGERPRINT
