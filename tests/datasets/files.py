"""One dataset written in every format by writers independent of the readers: the
csv module, numpy.savez, scipy.io.savemat (v5) and hdf5storage (MATLAB v7.3)."""

from __future__ import annotations

import csv
import io
import json

import numpy as np


def rollouts(seed: int = 3, *, lengths=(7, 4, 5), n: int = 3, m: int = 2):
    """Ragged rollouts of a seeded linear system (values with all 17 digits)."""
    rng = np.random.default_rng(seed)
    A = 0.8 * np.eye(n) + 0.02 * rng.standard_normal((n, n))  # stable: long rollouts stay O(1)
    B = rng.standard_normal((n, m))
    return simulate(A, B, rng, lengths=lengths)


def simulate(A, B, rng, *, lengths, sigma_w: float = 0.1):
    """Rollouts of x+ = A x + B u + w: Gaussian x_0, inputs and noise N(0, sigma_w^2)
    drawn from ``rng`` (a seed or a Generator), one rollout of T steps per length."""
    rng = np.random.default_rng(rng)
    A, B = np.asarray(A, dtype=float), np.asarray(B, dtype=float).reshape(len(A), -1)
    n, m = B.shape
    X, U = [], []
    for T in lengths:
        u = rng.standard_normal((T, m))
        x = np.zeros((T + 1, n))
        x[0] = rng.standard_normal(n)
        for k in range(T):
            x[k + 1] = A @ x[k] + B @ u[k] + sigma_w * rng.standard_normal(n)
        X.append(x)
        U.append(u)
    return X, U


def csv_bytes(X, U, *, states=None, inputs=None, labels=None, extra=None) -> bytes:
    """Long form: rollout, k, states, inputs (the last row of a rollout: no inputs)."""
    n, m = X[0].shape[1], U[0].shape[1]
    states = states or [f"x{i + 1}" for i in range(n)]
    inputs = inputs or [f"u{i + 1}" for i in range(m)]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["rollout", "k", *states, *inputs, *(extra or [])])
    for i, (x, u) in enumerate(zip(X, U)):
        for k in range(len(x)):
            us = [repr(float(v)) for v in u[k]] if k < len(u) else [""] * m
            label = labels[i] if labels else i
            w.writerow(
                [label, k, *(repr(float(v)) for v in x[k]), *us, *(["e"] * len(extra or []))]
            )
    return buf.getvalue().encode()


def npz_bytes(X, U, *, ragged: bool = True, **extra) -> bytes:
    buf = io.BytesIO()
    if ragged:
        arrays = {f"X_{i}": x for i, x in enumerate(X)}
        arrays.update({f"U_{i}": u for i, u in enumerate(U)} if U[0].shape[1] else {})
    else:
        arrays = {"X": np.array(X), **({"U": np.array(U)} if U[0].shape[1] else {})}
    np.savez(buf, **arrays, **extra)
    return buf.getvalue()


def _cells(arrays) -> np.ndarray:
    cell = np.empty((1, len(arrays)), dtype=object)
    for i, a in enumerate(arrays):
        cell[0, i] = a
    return cell


def mat5_bytes(X, U, **extra) -> bytes:
    import scipy.io

    buf = io.BytesIO()
    variables = {"X": _cells(X), **({"U": _cells(U)} if U[0].shape[1] else {}), **extra}
    scipy.io.savemat(buf, variables)
    return buf.getvalue()


def mat73_bytes(X, U, tmp_path, **extra) -> bytes:
    import hdf5storage

    path = tmp_path / "d73.mat"
    cells = {"X": _cells(X).reshape(-1)}
    if U[0].shape[1]:
        cells["U"] = _cells(U).reshape(-1)
    hdf5storage.savemat(str(path), {**cells, **extra}, format="7.3", matlab_compatible=True)
    return path.read_bytes()


def json_bytes(X, U, **extra) -> bytes:
    body = {"X": [x.tolist() for x in X]}
    if U[0].shape[1]:
        body["U"] = [u.tolist() for u in U]
    return json.dumps({**body, **extra}).encode()


def all_formats(X, U, tmp_path) -> dict[str, tuple[str, bytes]]:
    """{format: (file name, bytes)} of the same rollouts."""
    return {
        "csv": ("d.csv", csv_bytes(X, U)),
        "npz": ("d.npz", npz_bytes(X, U)),
        "mat": ("d.mat", mat5_bytes(X, U)),
        "mat73": ("d73.mat", mat73_bytes(X, U, tmp_path)),
        "json": ("d.json", json_bytes(X, U)),
    }
