"""compact results: matrices as float64 bytes, notes dictionary-coded, derived seed_key

The ``results`` table (0002's: with bounds_method and the radius matrices) is
rebuilt (both dialects) in the format of
``service.db.result_codec``: the matrix fields as little-endian float64 bytes
(shapes from the job's spec; a K constant over a (system, sigma_w) is written
once into the new ``result_constants`` by the worker, while converted rows keep
theirs inline), ``notes`` as an id into the new ``result_notes``,
``seed_key`` NULL when it is the spec's ``[system index, sigma_w index, N,
rep]`` (else its JSON text), the cell key as the primary key (no surrogate id,
SQLite WITHOUT ROWID), no secondary indexes (every per-job filter and the
results order use the key's prefix) and no foreign keys (a per-row trigger
check on PostgreSQL; see ``service.db.models.Result``). Rows are converted in batches; the
downgrade converts them back to the 0002 format.

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-01 09:30:00
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import sqlalchemy as sa
from alembic import op

from svrobs_core import resolve_system

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None

MATRICES = ("A_hat", "B_hat", "radii_A", "radii_B", "L", "K")
FLOATS = (
    "sigma_w",
    "gamma_key",
    "gamma",
    "rmse_A",
    "rmse_B",
    "H_A",
    "H_B",
    "r_A",
    "r_B",
    "eps_A",
    "eps_B",
    "coverage_A",
    "coverage_B",
    "rho_upper_bound",
    "g_L",
    "rho_true",
    "J_exact",
    "J_stationary",
    "J_mc",
    "J_mc_se",
    "J_star",
    "cost_ratio",
    "J_bound",
    "delta_J",
    "J_opt",
    "J_opt_bound",
)
INTS = ("job_id", "N", "N0", "rep")
BOOLS = ("thm1_holds_A", "thm1_holds_B", "stable_certified", "certified")
KEY = ("job_id", "system", "sigma_w", "N", "estimator", "gamma_key", "rep")
OLD_INDEXES = {
    "ix_results_job_N": ["job_id", "N"],
    "ix_results_job_estimator": ["job_id", "estimator", "gamma_key"],
    "ix_results_job_rep": ["job_id", "rep"],
    "ix_results_job_sigma": ["job_id", "sigma_w"],
}
BATCH = 2000


def _scalar_columns() -> list[sa.Column]:
    cols = [sa.Column(f, sa.Float(), nullable=f not in KEY) for f in FLOATS]
    cols += [sa.Column(f, sa.Integer(), nullable=f not in KEY) for f in INTS]
    return cols + [sa.Column(f, sa.Boolean(), nullable=True) for f in BOOLS]


def _create_compact(name: str) -> None:
    op.create_table(
        name,
        *_scalar_columns()[:-4],
        sa.Column("notes_id", sa.Integer(), nullable=True),
        *_scalar_columns()[-4:],
        sa.Column("system", sa.String(length=200), nullable=False),
        sa.Column("estimator", sa.String(length=32), nullable=False),
        sa.Column("bounds_method", sa.String(length=32), nullable=True),
        sa.Column("sls_status", sa.String(length=64), nullable=True),
        sa.Column("seed_key", sa.Text(), nullable=True),
        *[sa.Column(f, sa.LargeBinary(), nullable=True) for f in MATRICES],
        sa.PrimaryKeyConstraint(*KEY, name="pk_results"),
        sqlite_with_rowid=False,
    )


def _create_old(name: str) -> None:
    op.create_table(
        name,
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), nullable=False),
        sa.Column("job_id", sa.Integer(), nullable=False),
        sa.Column("system", sa.String(length=200), nullable=False),
        sa.Column("estimator", sa.String(length=32), nullable=False),
        sa.Column("gamma_key", sa.Float(), nullable=False),
        sa.Column("seed_key", sa.JSON(), nullable=True),
        sa.Column("sls_status", sa.String(length=64), nullable=True),
        sa.Column("notes", sa.Text(), nullable=True),
        *[c for c in _scalar_columns() if c.name not in ("job_id", "gamma_key")],
        *[sa.Column(f, sa.JSON(), nullable=True) for f in MATRICES if "radii" not in f],
        sa.Column("bounds_method", sa.String(length=32), nullable=True),  # 0002's columns
        sa.Column("radii_A", sa.JSON(), nullable=True),
        sa.Column("radii_B", sa.JSON(), nullable=True),
        sa.ForeignKeyConstraint(["job_id"], ["jobs.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint(*KEY, name="uq_results_cell"),
    )


class _Specs:
    """Per job: system name -> (n, m, p) and the spec's system / sigma_w indices (and
    its result_constants, when reading the compact format)."""

    def __init__(self, conn, constants: bool = False):
        self.conn, self.cache, self.constants = conn, {}, constants
        self.shared: dict[int, dict] = {}

    def __call__(self, job_id: int):
        if job_id not in self.cache:
            spec = self.conn.execute(
                sa.text("SELECT spec FROM jobs WHERE id = :id"), {"id": job_id}
            ).scalar_one()
            spec = json.loads(spec) if isinstance(spec, str) else spec
            systems = [resolve_system(s) for s in spec["systems"]]
            self.cache[job_id] = (
                {s.name: (s.n, s.m, s.p) for s in systems},
                {s.name: i for i, s in enumerate(systems)},
                {float(w): i for i, w in enumerate(spec["sigma_w"])},
            )
            if self.constants:
                rows = self.conn.execute(
                    sa.text(
                        "SELECT system, sigma_w, field, value FROM result_constants "
                        "WHERE job_id = :id"
                    ),
                    {"id": job_id},
                )
                self.shared[job_id] = {(s, float(w), f): bytes(v) for s, w, f, v in rows}
        return self.cache[job_id]


def _shape(field: str, n: int, m: int, p: int) -> tuple[int, int]:
    return {"A_hat": (n, n), "B_hat": (n, m), "L": (n, p), "K": (n, p)}.get(
        field, (n, n) if field == "radii_A" else (n, m)
    )


def _derived_seed(specs, row) -> list | None:
    _, si, wi = specs(row["job_id"])
    s, w = si.get(row["system"]), wi.get(float(row["sigma_w"]))
    return None if s is None or w is None else [s, w, int(row["N"]), int(row["rep"])]


def _stream(conn, query):
    result = conn.execute(query.execution_options(stream_results=True, yield_per=BATCH))
    for part in result.mappings().partitions(BATCH):
        yield [dict(r) for r in part]


def upgrade() -> None:
    conn = op.get_bind()
    op.create_table(
        "result_notes",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("digest", sa.String(length=64), nullable=False),
        sa.Column("text", sa.Text(), nullable=False),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("digest"),
    )
    op.create_table(
        "result_constants",
        sa.Column("job_id", sa.Integer(), nullable=False),
        sa.Column("system", sa.String(length=200), nullable=False),
        sa.Column("sigma_w", sa.Float(), nullable=False),
        sa.Column("field", sa.String(length=32), nullable=False),
        sa.Column("value", sa.LargeBinary(), nullable=False),
        sa.PrimaryKeyConstraint("job_id", "system", "sigma_w", "field"),
    )
    _create_compact("results_compact")
    old = sa.table(
        "results",
        *[sa.column(c) for c in ("id", "job_id", "system", "estimator", "sls_status", "notes")],
        sa.column("bounds_method"),
        *[sa.column(c) for c in FLOATS + INTS + BOOLS if c != "job_id"],
        *[sa.column(c) for c in ("seed_key",) + MATRICES],
    )
    new = sa.table(
        "results_compact", *[sa.column(c) for c in _new_names() + ("seed_key",) + MATRICES]
    )
    notes_t = sa.table("result_notes", sa.column("id"), sa.column("digest"), sa.column("text"))
    specs, notes = _Specs(conn), {None: None}
    cols = [old.c[c] for c in old.c.keys() if c not in ("seed_key",) + MATRICES]
    cols += [sa.cast(old.c[c], sa.Text).label(c) for c in ("seed_key",) + MATRICES]
    for rows in _stream(conn, sa.select(*cols).order_by(old.c.id)):
        for text in {r["notes"] for r in rows} - set(notes):
            digest = hashlib.sha256(text.encode()).hexdigest()
            conn.execute(notes_t.insert().values(digest=digest, text=text))
            notes[text] = conn.execute(
                sa.select(notes_t.c.id).where(notes_t.c.digest == digest)
            ).scalar_one()
        out = []
        for r in rows:
            seed = None if r["seed_key"] is None else json.loads(r["seed_key"])
            row = {c: r[c] for c in _new_names() if c in r and c not in MATRICES}
            row["seed_key"] = None if seed == _derived_seed(specs, r) else json.dumps(seed)
            row["notes_id"] = notes[r["notes"]]
            for f in MATRICES:
                v = None if r[f] is None else json.loads(r[f])
                row[f] = None if v is None else np.asarray(v, dtype="<f8").tobytes()
            out.append(row)
        conn.execute(new.insert(), out)
    op.drop_table("results")
    op.rename_table("results_compact", "results")


def _new_names() -> tuple[str, ...]:
    return FLOATS + INTS + ("notes_id",) + BOOLS + TEXTS


TEXTS = ("system", "estimator", "bounds_method", "sls_status")


def downgrade() -> None:
    conn = op.get_bind()
    _create_old("results_json")
    names = _new_names()
    cur = sa.table("results", *[sa.column(c) for c in names + ("seed_key",) + MATRICES])
    notes_t = sa.table("result_notes", sa.column("id"), sa.column("text"))
    old_names = [c for c in names if c != "notes_id"] + ["notes"]
    old = sa.table(
        "results_json",
        *[sa.column(c) for c in old_names],
        *[sa.column(c, sa.JSON()) for c in ("seed_key",) + MATRICES],
    )
    q = (
        sa.select(*cur.c, notes_t.c.text.label("notes"))
        .select_from(cur.outerjoin(notes_t, cur.c.notes_id == notes_t.c.id))
        .order_by(*(cur.c[k] for k in KEY))
    )
    specs = _Specs(conn, constants=True)
    for rows in _stream(conn, q):
        out = []
        for r in rows:
            dims = specs(r["job_id"])[0][r["system"]]
            row = {c: r[c] for c in old_names}
            seed = r["seed_key"]
            row["seed_key"] = _derived_seed(specs, r) if seed is None else json.loads(seed)
            for f in MATRICES:  # JSON-typed columns: the lists are serialised on insert
                b = r[f]
                if b is not None and len(b) == 0:  # the job's constant of (system, sigma_w)
                    b = specs.shared[r["job_id"]][(r["system"], float(r["sigma_w"]), f)]
                if b is not None:
                    shape = _shape(f, *dims)
                    size = shape[0] * shape[1]
                    b = bytes(b) * size if len(b) == 8 else bytes(b)  # one repeated float
                    a = np.frombuffer(b, dtype="<f8").reshape(shape)
                    b = np.where(np.isfinite(a), a, None).tolist()
                row[f] = b
            out.append(row)
        conn.execute(old.insert(), out)
    op.drop_table("results")
    op.drop_table("result_notes")
    op.drop_table("result_constants")
    op.rename_table("results_json", "results")
    with op.batch_alter_table("results", schema=None) as batch_op:
        for name, cols in OLD_INDEXES.items():
            batch_op.create_index(name, cols, unique=False)
