"""Where the client finds the server and the key: arguments, then the environment
(``SVROBS_URL``, ``SVROBS_API_KEY``), then the config file
(``SVROBS_CONFIG``, default ``~/.config/svrobs/config.json``: ``{"url", "api_key"}``)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import httpx

from .errors import ConfigError

DEFAULT_URL = "http://127.0.0.1:8000"


def config_path() -> Path:
    """The config file's path (``SVROBS_CONFIG`` or ``~/.config/svrobs/config.json``)."""
    return Path(os.environ.get("SVROBS_CONFIG", "~/.config/svrobs/config.json")).expanduser()


def _first(given: Any, env: str, cfg: dict[str, Any], key: str, path: Path) -> tuple[Any, str]:
    """The first value set, and where it comes from (for the messages)."""
    if given:
        return given, f"the {key} argument"
    if os.environ.get(env):
        return os.environ[env], env
    return cfg.get(key), f"{key!r} in {path}"


def _check_url(url: str, source: str) -> str:
    try:
        parsed = httpx.URL(url)
    except (httpx.InvalidURL, TypeError):
        parsed = None
    if parsed is None or parsed.scheme not in ("http", "https") or not parsed.host:
        raise ConfigError(f"{source}: {url!r} is not an http:// or https:// URL")
    url = url.rstrip("/")
    # the server's root is meant; the API's prefix given with it is taken off
    return url.removesuffix("/api/v1") if url.endswith("/api/v1") else url


def _check_key(key: str, source: str) -> str:
    if not (key.isascii() and key.isprintable()) or " " in key:
        raise ConfigError(
            f"{source}: the API key has a space, a line break or a non-ASCII character, "
            "which no API key has"
        )
    return key


def resolve(url: str | None = None, key: str | None = None) -> tuple[str, str]:
    """``(base URL without a trailing slash, API key)``; :class:`ConfigError` when no
    key is given anywhere, the URL is not http(s), the key has characters no key has
    (surrounding white space is dropped) or the config file cannot be read."""
    cfg: dict[str, Any] = {}
    path = config_path()
    if (url is None or key is None) and path.is_file():
        try:
            cfg = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ConfigError(f"cannot read {path}: {exc}") from None
        if not isinstance(cfg, dict):
            raise ConfigError(f"cannot read {path}: not a JSON object")
    url_value, url_source = _first(url, "SVROBS_URL", cfg, "url", path)
    key_value, key_source = _first(key, "SVROBS_API_KEY", cfg, "api_key", path)
    key_value = str(key_value).strip() if key_value else ""
    if not key_value:
        raise ConfigError(f"no API key: set SVROBS_API_KEY or 'api_key' in {path}")
    if not url_value:
        url_value, url_source = DEFAULT_URL, "the default URL"
    return _check_url(str(url_value), url_source), _check_key(key_value, key_source)
