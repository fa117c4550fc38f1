"""Logging, configured once per process: the API app factory, the CLI, and the
worker and beat processes (through Celery's ``setup_logging`` signal, see
:mod:`worker.celery_app`). Every module logs to ``logging.getLogger(__name__)``.
"""

from __future__ import annotations

import logging
import sys

from service.config import Settings

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
_HANDLER_NAME = "svrobs"


def configure_logging(settings: Settings) -> None:
    """One stream handler on the root logger (stderr: time, level, logger name) at
    ``settings.LOG_LEVEL``. Calling it again only updates the level."""
    root = logging.getLogger()
    root.setLevel(settings.LOG_LEVEL)
    if any(h.get_name() == _HANDLER_NAME for h in root.handlers):
        return
    handler = logging.StreamHandler(sys.stderr)
    handler.set_name(_HANDLER_NAME)
    handler.setFormatter(logging.Formatter(FORMAT))
    root.addHandler(handler)
