"""Write the example files of docs/datasets.md: one small dataset (3 rollouts of 5, 3
and 4 steps, n = 2 states, m = 1 input, values with 4 decimals) as CSV, NPZ, MATLAB
v5, MATLAB v7.3 and JSON, a system file (A, B, C) as NPZ, and ``plant.csv``, runs of
the same system long enough to fit and validate a model on (24 rollouts of 40 steps:
the README's measured-data tour).

    python docs/examples/make_examples.py        # rewrites the files beside it

The v7.3 file is written with h5py in MATLAB's layout (a 512-byte MAT header in the
HDF5 user block, arrays stored column-major with their MATLAB_class), so that
neither MATLAB nor hdf5storage is needed to make it.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
LENGTHS = (5, 3, 4)
SAMPLE_TIME = 0.1
A = np.array([[0.95, 0.1], [-0.1, 0.9]])
B = np.array([[0.0], [0.5]])
C = np.array([[1.0, 0.0]])


PLANT_RUNS = (40,) * 24


def rollouts(seed: int = 7, lengths=LENGTHS):
    """X_i (T_i+1, 2) and U_i (T_i, 1) of x+ = A x + B u + w, rounded to 4 decimals."""
    rng = np.random.default_rng(seed)
    X, U = [], []
    for T in lengths:
        u = np.round(rng.uniform(-1, 1, (T, 1)), 4)
        x = np.zeros((T + 1, 2))
        x[0] = rng.uniform(-1, 1, 2)
        for k in range(T):
            x[k + 1] = A @ x[k] + B @ u[k] + 0.05 * rng.standard_normal(2)
        X.append(np.round(x, 4))
        U.append(u)
    return X, U


def write_csv(path: Path, X, U) -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["rollout", "k", "x1", "x2", "u1"])
        for i, (x, u) in enumerate(zip(X, U)):
            for k in range(len(x)):
                inputs = [repr(float(u[k, 0]))] if k < len(u) else [""]
                w.writerow([i, k, *(repr(float(v)) for v in x[k]), *inputs])


def write_mat73(path: Path, variables: dict) -> None:
    """A MATLAB v7.3 file: HDF5 with MATLAB's 128-byte header in a 512-byte user block."""
    import h5py

    with h5py.File(path, "w", userblock_size=512) as f:
        for name, value in variables.items():
            d = f.create_dataset(name, data=np.asarray(value, dtype=np.float64).T)
            d.attrs["MATLAB_class"] = np.bytes_("double")
    text = b"MATLAB 7.3 MAT-file, Platform: svrobs, Created by: docs/examples/make_examples.py"
    text += b" HDF5 schema 1.00 ."
    header = text.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM"
    with path.open("r+b") as f:
        f.write(header.ljust(512, b"\x00"))


def main() -> None:
    import scipy.io

    X, U = rollouts()
    write_csv(HERE / "rollouts.csv", X, U)
    per_rollout = {f"X_{i}": x for i, x in enumerate(X)} | {f"U_{i}": u for i, u in enumerate(U)}
    np.savez(HERE / "rollouts.npz", **per_rollout)
    cells = {}
    for var, arrays in (("X", X), ("U", U)):
        cells[var] = np.empty((1, len(arrays)), dtype=object)
        for i, a in enumerate(arrays):
            cells[var][0, i] = a
    scipy.io.savemat(HERE / "rollouts_v5.mat", {**cells, "sample_time": SAMPLE_TIME})
    write_mat73(HERE / "rollouts_v73.mat", {**per_rollout, "sample_time": [[SAMPLE_TIME]]})
    head = {"sample_time": SAMPLE_TIME, "state_names": ["x1", "x2"], "input_names": ["u1"]}
    lines = [json.dumps(head)[:-1] + ","]  # one rollout a line
    for key, arrays in (("X", X), ("U", U)):
        rows = ",\n  ".join(json.dumps(a.tolist()) for a in arrays)
        lines.append(f' "{key}": [\n  {rows}\n ]' + ("," if key == "X" else ""))
    (HERE / "rollouts.json").write_text("\n".join(lines) + "\n}\n")
    np.savez(HERE / "system.npz", A=A, B=B, C=C)
    write_csv(HERE / "plant.csv", *rollouts(seed=11, lengths=PLANT_RUNS))


if __name__ == "__main__":
    main()
