"""Files the client writes: whole or not at all."""

from __future__ import annotations

import errno
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import IO


def writer(data: bytes) -> Callable[[IO[bytes]], object]:
    """``write`` for :func:`write_atomic`: the file gets ``data``."""
    return lambda f: f.write(data)


def _cannot_write(path: Path, exc: OSError) -> OSError:
    """``exc`` as an error naming ``path`` (not a temporary file) and why in plain words:
    a folder on the way that is a file, ``path`` itself a folder, or the system's reason."""
    for folder in path.parents:  # the nearest that exists decides
        if folder.exists():
            if not folder.is_dir():
                message = f"cannot write {path}: {folder} is not a folder"
                return NotADirectoryError(errno.ENOTDIR, message)
            break
    if path.is_dir():
        return IsADirectoryError(errno.EISDIR, f"cannot write {path}: it is a folder")
    reason = exc.strerror or str(exc)
    return type(exc)(exc.errno, f"cannot write {path}: {reason}")


def _mode_for(path: Path) -> int:
    """The permissions ``path`` gets: those it has if it exists, else those ``open``
    gives a new file (0o666 less the process's umask)."""
    try:
        return stat.S_IMODE(path.stat().st_mode)
    except OSError:
        pass
    try:  # Linux: the umask without changing it
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def write_atomic(path: Path, write: Callable[[IO[bytes]], object]) -> None:
    """Write through ``write(file)`` into a temporary file beside ``path``, then rename it:
    ``path`` appears complete or not at all, with the permissions a file written in
    place would have (:func:`_mode_for`; the temporary file is private). The folder is
    made if needed; an OSError that it or the file cannot be made names ``path``
    (:func:`_cannot_write`)."""
    import tempfile

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    except OSError as exc:
        raise _cannot_write(path, exc) from None
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        try:
            os.chmod(tmp, _mode_for(path))
            os.replace(tmp, path)
        except OSError as exc:
            raise _cannot_write(path, exc) from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
