"""What produced a job's records: package version, git commit, Python and numpy.

Stored on every job (``jobs.provenance``) with the spec's seed.
"""

from __future__ import annotations

import importlib.metadata
import platform
import subprocess
from functools import lru_cache
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent.parent


def git_commit(configured: str | None = None) -> str | None:
    """``configured`` (SVROBS_GIT_COMMIT, passed in by the caller), else ``git rev-parse
    HEAD`` of the checkout, else None."""
    if configured:
        return configured
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=2,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return (out.stdout.strip() or None) if out.returncode == 0 else None


@lru_cache
def _static_provenance(configured_commit: str | None) -> dict:
    version: str | None
    try:
        version = importlib.metadata.version("svrobs")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover
        import svrobs_core

        version = getattr(svrobs_core, "__version__", None)
    import numpy

    return {
        "package": "svrobs",
        "version": version,
        "git_commit": git_commit(configured_commit),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "platform": platform.platform(),
    }


def provenance(seed: int, git_commit: str | None = None) -> dict:
    """The provenance of a job run with ``seed``; ``git_commit``: SVROBS_GIT_COMMIT
    (None: the checkout's, :func:`git_commit`)."""
    return {**_static_provenance(git_commit), "seed": seed}
