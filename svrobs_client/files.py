"""Files the client writes: whole or not at all."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import IO


def writer(data: bytes) -> Callable[[IO[bytes]], object]:
    """``write`` for :func:`write_atomic`: the file gets ``data``."""
    return lambda f: f.write(data)


def write_atomic(path: Path, write: Callable[[IO[bytes]], object]) -> None:
    """Write through ``write(file)`` into a temporary file beside ``path``, then rename it:
    ``path`` appears complete or not at all."""
    import tempfile

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
