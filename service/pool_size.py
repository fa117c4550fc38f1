"""How many pool processes a worker runs by default (``SVROBS_WORKER_POOL_PROCESSES``):
a module of its own, so that the CLI reads it without importing the settings."""

from __future__ import annotations

import os


def default_pool_processes() -> int:
    """One pool process per CPU plus one, at most 5: what ``svrobs serve`` starts."""
    return max(1, min((os.cpu_count() or 1) + 1, 5))
