"""The typed core errors and the one shape check (svrobs_core.errors)."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import svrobs_core
from svrobs_core import DimensionError, SpecError, check_matrix
from svrobs_core.cost import exact_cost
from svrobs_core.gains import design_gain
from svrobs_core.kalman import kalman_predictor
from svrobs_core.norms import h2_norm


def test_check_matrix_accepts_and_returns_float_arrays():
    a = check_matrix("A", [[1, 2], [3, 4]], ("n", "n"))
    assert a.dtype == float and a.shape == (2, 2)
    b = check_matrix("B", np.zeros((5, 7, 2, 3)), (2, None))
    assert b.shape == (5, 7, 2, 3)
    assert check_matrix("K", np.ones((3, 2)), (3, 2), batch=False).shape == (3, 2)


@pytest.mark.parametrize(
    ("array", "shape", "batch"),
    [
        (np.zeros((2, 3)), ("n", "n"), True),  # not square
        (np.zeros(3), (None, None), True),  # too few axes
        (np.zeros((4, 3, 3)), (3, 3), False),  # batch axes not allowed
        (np.zeros((3, 2)), (3, 3), True),  # wrong size
    ],
)
def test_check_matrix_rejects_with_a_dimension_error(array, shape, batch):
    with pytest.raises(DimensionError) as e:
        check_matrix("X", array, shape, batch=batch)
    assert isinstance(e.value, ValueError) and not isinstance(e.value, SpecError)
    assert e.value.name == "X" and str(array.shape) in str(e.value)


def test_core_functions_raise_dimension_errors_for_shapes():
    eye = np.eye(3)
    with pytest.raises(DimensionError, match="A"):
        kalman_predictor(np.zeros((3, 2)), eye, 1.0, 0.1)
    with pytest.raises(DimensionError, match="K_hat"):
        design_gain(eye, 0.0, 0.01, eye, K_hat=np.zeros((3, 2)))
    with pytest.raises(DimensionError, match="L"):
        exact_cost(
            eye, np.ones((3, 1)), eye, np.ones((3, 1)),
            L=np.zeros((2, 3)), C=eye, sigma_u=1.0, sigma_w=1.0, sigma_v=1.0,
        )  # fmt: skip
    with pytest.raises(DimensionError, match="G"):
        h2_norm(0.5 * eye, np.ones((2, 1)), eye)


def test_spec_error_names_the_field():
    e = SpecError("systems[0].A", "must be square")
    assert isinstance(e, ValueError) and e.field == "systems[0].A"
    assert str(e) == "systems[0].A: must be square"


def test_package_exports_resolve_and_threads_import_without_numpy():
    for name in svrobs_core.__all__:
        assert getattr(svrobs_core, name) is not None
    code = (
        "import sys, os; from svrobs_core.threads import single_thread_env, THREAD_ENV;"
        "single_thread_env(); assert 'numpy' not in sys.modules;"
        "assert all(os.environ[k] for k in THREAD_ENV)"
    )
    root = str(Path(svrobs_core.__file__).resolve().parent.parent)
    env = {k: v for k, v in os.environ.items() if not k.endswith(("_THREADS", "_NUM_THREADS"))}
    subprocess.run([sys.executable, "-c", code], check=True, env={**env, "PYTHONPATH": root})
