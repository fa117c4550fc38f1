"""What ``docker build .`` of the repository would make, without a Docker engine.

:func:`context_files` is the build context: the files ``.dockerignore`` lets through
(Docker's rules: patterns in order, the last one matching a path or one of its parent
folders decides, ``!`` lets through, ``**`` spans folders). :func:`parse` reads the
Dockerfile into an :class:`Image`: the base, ENV (with ARG and ``${...}`` substituted),
WORKDIR, USER, CMD, and the build steps in order: the files each COPY takes, and the
commands of each RUN line. A RUN command the model does not know (only ``pip install``,
``useradd``, ``mkdir`` and ``chown`` are) fails the parse, naming it, instead of being
skipped. :func:`build` carries the steps out under a folder: the COPYed files, then the
RUN pip line against a fresh virtual environment (see :mod:`tests.deploy.python_env`).
"""

from __future__ import annotations

import json
import os
import posixpath
import re
import shlex
import shutil
import sys
import time
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from pathlib import Path

from tests.deploy.python_env import ImagePython

# -------------------------------------------------------------- .dockerignore


def ignore_rules(text: str) -> list[tuple[bool, list[str]]]:
    """``.dockerignore`` lines as (lets_through, pattern segments), in order."""
    rules = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        through = line.startswith("!")
        pattern = posixpath.normpath(line[1:].strip() if through else line).lstrip("/")
        rules.append((through, pattern.split("/")))
    return rules


def _segment(name: str, pattern: str) -> bool:
    # Go's filepath.Match negates a class with ^, fnmatch with !
    return fnmatchcase(name, pattern.replace("[^", "[!").replace("**", "*"))


def _match(psegs: list[str], segs: list[str]) -> bool:
    if not psegs:
        return not segs
    if psegs[0] == "**":
        return any(_match(psegs[1:], segs[i:]) for i in range(len(segs) + 1))
    return bool(segs) and _segment(segs[0], psegs[0]) and _match(psegs[1:], segs[1:])


def excluded(rules, path: str) -> bool:
    """Whether ``path`` (relative to the context, ``/``-separated) stays out."""
    segs = path.split("/")
    out = False
    for through, psegs in rules:
        if any(_match(psegs, segs[:n]) for n in range(1, len(segs) + 1)):
            out = not through
    return out


def _may_let_through_under(rules, folder: str) -> bool:
    """Whether some ``!`` rule could match a path inside an excluded ``folder``."""
    dsegs = folder.split("/")
    for through, psegs in rules:
        if not through:
            continue
        for i, d in enumerate(dsegs):
            if i >= len(psegs):
                break
            if psegs[i] == "**":
                return True
            if not _segment(d, psegs[i]):
                break
        else:
            if len(psegs) > len(dsegs):
                return True
    return False


def context_files(context: Path) -> list[str]:
    """The files of the build context at ``context``, ``/``-separated and sorted."""
    ignore = context / ".dockerignore"
    rules = ignore_rules(ignore.read_text()) if ignore.exists() else []
    files = []
    for here, dirs, names in os.walk(context):
        rel = Path(here).relative_to(context).as_posix()
        prefix = "" if rel == "." else rel + "/"
        dirs[:] = sorted(
            d
            for d in dirs
            if not excluded(rules, prefix + d) or _may_let_through_under(rules, prefix + d)
        )
        files += [prefix + n for n in names if not excluded(rules, prefix + n)]
    return sorted(files)


# -------------------------------------------------------------- Dockerfile


class Unsupported(AssertionError):
    """A Dockerfile instruction or RUN command this model cannot reproduce."""


@dataclass
class Image:
    base: str = ""
    env: dict[str, str] = field(default_factory=dict)
    workdir: str = "/"
    user: str | None = None
    cmd: list[str] = field(default_factory=list)
    exposed: list[int] = field(default_factory=list)
    # ("copy", {container path: context path}) | ("pip", argv after pip, workdir, env)
    # | ("mkdir", path) | ("chown", user, path) | ("useradd", name, home or None)
    steps: list[tuple] = field(default_factory=list)

    @property
    def files(self) -> dict[str, str]:
        """Every file COPY puts in the image: container path -> context path."""
        out: dict[str, str] = {}
        for step in self.steps:
            if step[0] == "copy":
                out.update(step[1])
        return out

    @property
    def homes(self) -> dict[str, str | None]:
        return {s[1]: s[2] for s in self.steps if s[0] == "useradd"}

    def state_dirs(self) -> dict[str, bool]:
        """The folders RUN made outside WORKDIR: path -> whether USER owns it."""
        out: dict[str, bool] = {}
        for step in self.steps:
            if step[0] == "mkdir":
                out.setdefault(step[1], False)
            elif step[0] == "useradd" and step[2]:
                out[step[2]] = step[1] == self.user
            elif step[0] == "chown":
                out[step[2]] = step[1].split(":")[0] == self.user
        return out


_VAR = re.compile(r"\$(?:\{(\w+)(?::([-+])([^}]*))?\}|(\w+))")


def substitute(text: str, env: dict[str, str]) -> str:
    """Docker's ``$VAR``, ``${VAR}``, ``${VAR:-default}``, ``${VAR:+alt}``."""

    def one(m: re.Match) -> str:
        name = m.group(1) or m.group(4)
        value = env.get(name, "")
        if m.group(2) == "-":
            return value or m.group(3)
        if m.group(2) == "+":
            return m.group(3) if value else ""
        return value

    return _VAR.sub(one, text)


def instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with continuation lines joined, comments dropped."""
    out, current = [], ""
    for raw in text.splitlines():
        line = raw.strip()
        if line.startswith("#") or (not line and not current):
            continue
        if line.endswith("\\"):
            current += line[:-1] + " "
            continue
        current += line
        word, _, rest = current.strip().partition(" ")
        out.append((word.upper(), rest.strip()))
        current = ""
    return out


def _argv(args: str) -> list[str] | None:
    """The JSON (exec) form's list, else None."""
    if args.startswith("["):
        value = json.loads(args)
        assert isinstance(value, list) and all(isinstance(v, str) for v in value), args
        return value
    return None


def _container_path(path: str, workdir: str) -> str:
    return posixpath.normpath(posixpath.join(workdir, path))


def _copy(args: str, env, workdir: str, context: list[str]) -> dict[str, str]:
    words = _argv(args) or shlex.split(args)
    flags = [w for w in words if w.startswith("--")]
    words = [w for w in words if not w.startswith("--")]
    for flag in flags:
        if not flag.startswith(("--chown=", "--chmod=", "--link")):
            raise Unsupported(f"COPY {flag}: not modelled (one stage, files of the context)")
    *sources, dest = [substitute(w, env) for w in words]
    folders = set()
    for f in context:
        parts = f.split("/")[:-1]
        folders |= {"/".join(parts[:n]) for n in range(1, len(parts) + 1)}
    out: dict[str, str] = {}
    for src in sources:
        src = posixpath.normpath(src).lstrip("/")
        matches = (
            [p for p in sorted(set(context) | folders) if _match(src.split("/"), p.split("/"))]
            if any(c in src for c in "*?[")
            else [src]
        )
        for match in matches:
            if match in context:  # a file
                to_folder = dest.endswith("/") or len(sources) > 1 or len(matches) > 1
                target = posixpath.join(dest, posixpath.basename(match)) if to_folder else dest
                out[_container_path(target, workdir)] = match
                continue
            under = context if match == "." else [f for f in context if f.startswith(match + "/")]
            if not under:
                raise Unsupported(f"COPY {src}: not in the build context (see .dockerignore)")
            for f in under:
                rel = f if match == "." else f[len(match) + 1 :]
                out[_container_path(posixpath.join(dest, rel), workdir)] = f
    return out


def _run_commands(line: str, env, workdir: str) -> list[tuple]:
    argv = _argv(line)
    tokens = argv if argv is not None else _shell_words(substitute(line, env))
    steps, commands, current = [], [], []
    for tok in tokens + ["&&"]:
        if tok == "&&":
            commands.append(current)
            current = []
        else:
            current.append(tok)
    for cmd in commands:
        steps += _run_command(cmd, env, workdir, line)
    return steps


def _shell_words(line: str) -> list[str]:
    lex = shlex.shlex(line, posix=True, punctuation_chars=True)
    lex.whitespace_split = True
    words = list(lex)
    for w in words:
        if w and set(w) <= set("&|;<>()") and w != "&&":
            raise Unsupported(f"RUN {line!r}: the shell operator {w!r} is not modelled")
    return words


def _run_command(cmd: list[str], env, workdir: str, line: str) -> list[tuple]:
    if not cmd:
        raise Unsupported(f"RUN {line!r}: an empty command")
    name, args = cmd[0], cmd[1:]
    if name in ("python", "python3") and args[:2] == ["-m", "pip"]:
        name, args = "pip", args[2:]
    if name in ("pip", "pip3") and args[:1] == ["install"]:
        return [("pip", args, workdir, dict(env))]
    if name == "mkdir":
        return [("mkdir", _container_path(a, workdir)) for a in args if not a.startswith("-")]
    if name == "chown":
        owner, *paths = [a for a in args if not a.startswith("-")]
        return [("chown", owner, _container_path(p, workdir)) for p in paths]
    if name == "useradd":
        home, create, rest = None, False, list(args)
        while rest:
            a = rest.pop(0)
            if a in ("-m", "--create-home"):
                create = True
            elif a in ("-d", "--home-dir"):
                home = rest.pop(0)
            elif a in ("-u", "--uid", "-g", "--gid", "-s", "--shell", "-G", "--groups"):
                rest.pop(0)
            elif a in ("-r", "--system", "-l", "--no-log-init", "-U", "--user-group"):
                pass
            elif a.startswith("-"):
                raise Unsupported(f"RUN useradd {a}: not modelled")
            else:
                user = a
        return [("useradd", user, (home or f"/home/{user}") if create else None)]
    raise Unsupported(
        f"RUN {' '.join(cmd)!r}: tests/deploy/dockerfile.py models only pip install, "
        "useradd, mkdir and chown"
    )


def parse(dockerfile: Path, context: Path, build_args: dict[str, str] | None = None) -> Image:
    """The image ``dockerfile`` describes, built from ``context``."""
    files = context_files(context)
    image = Image()
    args: dict[str, str] = {}  # ARG values: substituted, never in the running image
    stages = 0
    for word, rest in instructions(dockerfile.read_text()):
        scope = {**args, **image.env}
        if word == "FROM":
            stages += 1
            if stages > 1:
                raise Unsupported("a second FROM: multi-stage builds are not modelled")
            image.base = substitute(rest, scope)
        elif word == "ARG":
            name, _, default = rest.partition("=")
            args[name] = (build_args or {}).get(name, default)
        elif word == "ENV":
            words = shlex.split(rest)
            pairs = (
                [w.partition("=")[::2] for w in words]
                if "=" in words[0]
                else [(words[0], " ".join(words[1:]))]
            )
            image.env.update({k: substitute(v, scope) for k, v in pairs})
        elif word == "WORKDIR":
            image.workdir = _container_path(substitute(rest, scope), image.workdir)
        elif word == "COPY":
            image.steps.append(("copy", _copy(rest, scope, image.workdir, files)))
        elif word == "RUN":
            image.steps += _run_commands(rest, scope, image.workdir)
        elif word == "USER":
            image.user = substitute(rest, scope).split(":")[0]
        elif word == "EXPOSE":
            image.exposed += [int(p.split("/")[0]) for p in substitute(rest, scope).split()]
        elif word == "CMD":
            image.cmd = _argv(rest) or ["/bin/sh", "-c", rest]
        elif word != "LABEL":
            raise Unsupported(f"{word}: not modelled by tests/deploy/dockerfile.py")
    return image


# -------------------------------------------------------------- build


@dataclass
class Built:
    image: Image
    root: Path  # the image's files: root / "app" is /app
    python: ImagePython
    seconds: dict[str, float] = field(default_factory=dict)

    def host_path(self, container_path: str) -> Path:
        return self.root / container_path.lstrip("/")


def build(image: Image, context: Path, into: Path, *, timeout: float = 300) -> Built:
    """Carry ``image``'s steps out under ``into``: the COPYed files under
    ``into/image``, every RUN pip line with the image's interpreter
    (:class:`ImagePython`), the folders RUN makes."""
    root = into / "image"
    root.mkdir(parents=True)
    python = ImagePython(into / "python")
    built = Built(image, root, python)
    for step in image.steps:
        if step[0] == "copy":
            for target, source in step[1].items():
                dest = built.host_path(target)
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(context / source, dest)
        elif step[0] == "pip":
            _, pip_args, workdir, env = step
            if not python.ready:
                t0 = time.monotonic()
                pyproject = built.host_path(posixpath.join(workdir, "pyproject.toml"))
                python.create(pyproject)
                built.seconds["venv"] = time.monotonic() - t0
            t0 = time.monotonic()
            run_env = {k: _host_value(v, built) for k, v in env.items()}
            proc = python.pip(pip_args, cwd=built.host_path(workdir), env=run_env, timeout=timeout)
            built.seconds["pip"] = time.monotonic() - t0
            if proc.returncode != 0:
                raise AssertionError(f"RUN pip {' '.join(pip_args)} failed:\n{proc.stdout[-6000:]}")
        elif step[0] == "mkdir":
            built.host_path(step[1]).mkdir(parents=True, exist_ok=True)
        elif step[0] == "useradd" and step[2]:
            built.host_path(step[2]).mkdir(parents=True, exist_ok=True)
    return built


def _host_value(value: str, built: Built) -> str:
    """PYTHONPATH=/app and the like, pointed at the image's folder on this machine."""
    parts = value.split(":")
    if all(p.startswith("/") for p in parts):
        return ":".join(str(built.host_path(p)) for p in parts)
    return value


def python_version(base: str) -> str | None:
    """``3.11`` for ``python:3.11-slim``; None for another base."""
    m = re.fullmatch(r"(?:docker\.io/)?(?:library/)?python:(\d+\.\d+)[\w.-]*", base)
    return m.group(1) if m else None


def this_python() -> str:
    return f"{sys.version_info.major}.{sys.version_info.minor}"
