"""The image's Python, made in seconds: a fresh virtual environment that sees exactly
the distributions ``pip install .`` would install for pyproject's dependencies.

The virtual environment has no site packages of its own and no pip. A ``.pth`` file
adds one folder to its ``sys.path``, holding links to the files of each distribution
in the closure of pyproject's ``[project].dependencies`` (extras and markers
evaluated), taken from this test environment: nothing else this environment has
(the test extras, the editable svrobs) is visible. Their console scripts
(``uvicorn``, ``celery``) are written into the environment's ``bin`` as pip writes
them. The Dockerfile's ``pip install`` then runs for real (pip of this environment,
``--python`` the new one, with build isolation: setuptools comes through this
machine's package index): it builds and installs svrobs, and finds every dependency
already satisfied, or fails as the image's build would when one is missing.
"""

from __future__ import annotations

import importlib.metadata as md
import os
import subprocess
import sys
import tomllib
import venv
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name


def dependency_closure(requirements: list[str]) -> dict[str, md.Distribution]:
    """The installed distributions that ``requirements`` pull in, by canonical name."""
    out: dict[str, md.Distribution] = {}
    extras_done: dict[str, set[str]] = {}
    queue = [r for r in map(Requirement, requirements) if _wanted(r, {""})]
    while queue:
        req = queue.pop()
        key = canonicalize_name(req.name)
        try:
            dist = md.distribution(req.name)
        except md.PackageNotFoundError:
            raise AssertionError(
                f"{req} (a dependency of the image) is not installed here: `make install`"
            ) from None
        if not req.specifier.contains(dist.version, prereleases=True):
            raise AssertionError(f"{req}: this environment has {dist.version}")
        extras = set(req.extras) | {""}
        if key in extras_done and extras <= extras_done[key]:
            continue
        extras_done[key] = extras_done.get(key, set()) | extras
        out[key] = dist
        queue += [r for r in map(Requirement, dist.requires or []) if _wanted(r, extras_done[key])]
    return out


def _wanted(req: Requirement, extras: set[str]) -> bool:
    return req.marker is None or any(req.marker.evaluate({"extra": e}) for e in extras)


def top_level_entries(dist: md.Distribution) -> tuple[Path, set[str]]:
    """The site folder of ``dist`` and the names of its entries there."""
    site = Path(dist.locate_file(""))
    names = {
        Path(f).parts[0]
        for f in dist.files or []
        if Path(f).parts[0] not in ("..", "__pycache__") and not str(f).startswith("/")
    }
    return site, names


class ImagePython:
    """The interpreter the image's services run: ``folder/venv/bin/python``."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.venv = folder / "venv"
        self.bin = self.venv / "bin"
        self.exe = self.bin / "python"
        self.site = folder / "dependencies"

    @property
    def ready(self) -> bool:
        return self.exe.exists()

    def create(self, pyproject: Path) -> None:
        """The environment, with pyproject's runtime dependencies and their scripts."""
        venv.EnvBuilder(with_pip=False, symlinks=True, clear=True).create(self.venv)
        requirements = tomllib.loads(pyproject.read_text())["project"]["dependencies"]
        self.site.mkdir(parents=True)
        for dist in dependency_closure(requirements).values():
            site, names = top_level_entries(dist)
            for name in names:
                link = self.site / name
                if not link.exists() and (site / name).exists():
                    link.symlink_to(site / name)
            for ep in dist.entry_points:
                if ep.group == "console_scripts":
                    self._script(ep)
        purelib = subprocess.run(
            [str(self.exe), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        Path(purelib, "image-dependencies.pth").write_text(f"{self.site}\n")

    def _script(self, ep: md.EntryPoint) -> None:
        head = ep.attr.split(".")[0]
        path = self.bin / ep.name
        path.write_text(
            f"#!{self.exe}\nimport sys\nfrom {ep.module} import {head}\n"
            f'if __name__ == "__main__":\n    sys.exit({ep.attr}())\n'
        )
        path.chmod(0o755)

    def pip(self, args: list[str], *, cwd: Path, env: dict, timeout: float):
        """``pip ARGS`` as the Dockerfile's RUN line runs it, into this environment."""
        machine = {k: v for k, v in os.environ.items() if k.startswith("PIP_")}
        run_env = {
            **machine,  # this machine's package index set-up (build isolation's setuptools)
            "PATH": f"{self.bin}:/usr/local/sbin:/usr/sbin:/usr/bin:/sbin:/bin",
            "HOME": str(self.folder),
            "LANG": "C.UTF-8",
            **env,
        }
        return subprocess.run(
            [sys.executable, "-m", "pip", "--python", str(self.exe), *args],
            cwd=str(cwd),
            env=run_env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=timeout,
            check=False,
        )
