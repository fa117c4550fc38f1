"""Where the client finds the server and the key: arguments, then the environment
(``SVROBS_URL``, ``SVROBS_API_KEY``), then the config file
(``SVROBS_CONFIG``, default ``~/.config/svrobs/config.json``: ``{"url", "api_key"}``)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from .errors import ConfigError

DEFAULT_URL = "http://127.0.0.1:8000"


def config_path() -> Path:
    """The config file's path (``SVROBS_CONFIG`` or ``~/.config/svrobs/config.json``)."""
    return Path(os.environ.get("SVROBS_CONFIG", "~/.config/svrobs/config.json")).expanduser()


def resolve(url: str | None = None, key: str | None = None) -> tuple[str, str]:
    """``(base URL without a trailing slash, API key)``; :class:`ConfigError` when no
    key is given anywhere or the config file cannot be read."""
    cfg: dict[str, Any] = {}
    path = config_path()
    if (url is None or key is None) and path.is_file():
        try:
            cfg = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ConfigError(f"cannot read {path}: {exc}") from None
        if not isinstance(cfg, dict):
            raise ConfigError(f"cannot read {path}: not a JSON object")
    url = url or os.environ.get("SVROBS_URL") or cfg.get("url") or DEFAULT_URL
    key = key or os.environ.get("SVROBS_API_KEY") or cfg.get("api_key")
    if not key:
        raise ConfigError(f"no API key: set SVROBS_API_KEY or 'api_key' in {path}")
    return str(url).rstrip("/"), str(key)
