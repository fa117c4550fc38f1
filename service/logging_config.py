"""Logging configured once per process (the API factory, ``svrobs serve``).

Minimal stand-in written by the api branch against the name the db branch defines
(``configure_logging(settings)``); the db branch's version (SVROBS_LOG_LEVEL) replaces it.
"""

from __future__ import annotations

import logging

from service.config import Settings

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def configure_logging(settings: Settings) -> None:
    """Send records of level INFO and above to stderr, unless logging is set up already."""
    logging.basicConfig(level=logging.INFO, format=FORMAT)
