"""``docker compose up`` of docker-compose.yml, with the image of :mod:`tests.deploy.dockerfile`,
on this machine: each service of the image is a real process, started in the
``depends_on`` order and with the conditions the file gives.

What a container would be, each process is: its command from the compose file, run
from the image's WORKDIR; its environment only the base image's (PATH, LANG), HOME,
the image's ENV and the service's ``environment`` (nothing of this test's own); its
files the image's, read-only to it, plus the folders the Dockerfile gives USER and the
service's volumes, its own (a named volume shared by the services that mount it).
Container paths are mapped onto folders here; the servers the compose file names
(``postgres``, ``redis``) onto this machine's PostgreSQL and Redis; container ports
onto free loopback ports. As root, a service runs as root without capabilities
(``setpriv``), the image's files owned by another user, so that it can write what
USER could write and nothing else.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

import yaml
from sqlalchemy.engine import make_url

from svrobs_cli.processes import Child, stop_all
from tests.deploy.dockerfile import Built
from tests.integration.stack import free_port

# the base image's environment (python:*), /usr/local/bin being the image's Python
BASE_PATH = "/usr/local/sbin:/usr/sbin:/usr/bin:/sbin:/bin"
DROP_CAPS = ["setpriv", "--inh-caps=-all", "--bounding-set=-all", "--"]
OTHER_UID = 65534  # owns the image's files when the services run as root
_INTERP = re.compile(r"\$\$|\$\{(\w+)(?:(:?[-?])([^}]*))?\}|\$(\w+)")


def interpolate(value, env: dict[str, str]):
    """Compose's ``${VAR}``, ``${VAR:-default}``, ``${VAR-default}``, ``${VAR:?error}``
    and ``$$`` in every string of ``value``."""
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def one(m: re.Match) -> str:
        if m.group(0) == "$$":
            return "$"
        name, op, word = m.group(1) or m.group(4), m.group(2), m.group(3)
        have = env.get(name)
        if op in (":-", ":?") and not have or op in ("-", "?") and have is None:
            if op.endswith("?"):
                raise AssertionError(f"${{{name}}} must be set: {word}")
            return word
        return have or ""

    return _INTERP.sub(one, value)


def load(path: Path, env: dict[str, str]) -> dict:
    """docker-compose.yml with anchors merged and variables interpolated."""
    return interpolate(yaml.safe_load(path.read_text()), env)


def environment(service: dict) -> dict[str, str]:
    env = service.get("environment") or {}
    if isinstance(env, list):
        env = dict(item.partition("=")[::2] for item in env)
    return {k: "" if v is None else str(v) for k, v in env.items()}


def seconds(text: str | int | float | None, default: float) -> float:
    if text is None:
        return default
    if isinstance(text, (int, float)):
        return float(text)
    total = 0.0
    for amount, unit in re.findall(r"(\d+(?:\.\d+)?)(ms|s|m|h)", text):
        total += float(amount) * {"ms": 0.001, "s": 1, "m": 60, "h": 3600}[unit]
    return total


class Deployment:
    """The compose file's services of the image at ``built``, under ``folder``.

    ``servers`` maps a compose service that is a server (``postgres``) to the URL of
    the machine's one standing in for it; ``extra_env`` adds variables to a service."""

    def __init__(
        self,
        built: Built,
        compose: dict,
        folder: Path,
        servers: dict[str, str],
        extra_env: dict[str, dict[str, str]] | None = None,
    ):
        self.built = built
        self.image = built.image
        self.compose = compose
        self.services: dict[str, dict] = compose["services"]
        self.ours = [n for n, s in self.services.items() if "build" in s]
        self.folder = folder
        self.servers = servers
        self.extra_env = extra_env or {}
        self.logs = folder / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.children: dict[str, Child] = {}
        self.as_root = os.geteuid() == 0
        exposed = set(self.image.exposed)
        for s in self.services.values():
            for p in s.get("ports") or []:
                exposed.add(int(str(p).split(":")[-1].split("/")[0]))
        self.ports = {p: free_port() for p in sorted(exposed)}
        self._seal()

    # ------------------------------------------------------------ files
    def _seal(self) -> None:
        """Make the image's files read-only to the services (their USER's view)."""
        trees = [self.built.root, self.built.python.folder]
        for tree in trees:
            for here, dirs, files in os.walk(tree):
                for name in [*dirs, *files, ""]:
                    path = Path(here, name)
                    if path.is_symlink():
                        continue
                    if self.as_root:
                        os.chown(path, OTHER_UID, OTHER_UID)
                    else:
                        path.chmod(path.stat().st_mode & ~0o222)

    def unseal(self) -> None:
        """Writable again by this test (before removing the folder)."""
        if self.as_root:
            return
        for here, dirs, files in os.walk(self.folder):
            for name in [*dirs, *files, ""]:
                path = Path(here, name)
                if not path.is_symlink():
                    path.chmod(path.stat().st_mode | 0o200)

    def _mounts(self, name: str) -> dict[str, Path]:
        """Container path -> folder here, for service ``name``: the image's WORKDIR,
        its state folders (this container's own) and the service's volumes."""
        mounts = {self.image.workdir: self.built.host_path(self.image.workdir)}
        for path, mine in self.image.state_dirs().items():
            mounts[path] = self._own_folder(self.folder / "containers" / name, path, mine)
        for volume in self.services[name].get("volumes") or []:
            source, _, target = str(volume).partition(":")
            target = target.split(":")[0]
            assert not source.startswith((".", "/")), f"{name}: bind mount {volume} is not modelled"
            mine = self.image.state_dirs().get(target, False)
            mounts[target] = self._own_folder(self.folder / "volumes" / source, "", mine)
        return mounts

    def _own_folder(self, base: Path, path: str, mine: bool) -> Path:
        folder = base / path.lstrip("/")
        if not folder.exists():
            folder.mkdir(parents=True)
            for p in [folder, *folder.parents]:
                if p == self.folder:
                    break
                p.chmod(0o755)
            if not mine:
                if self.as_root:
                    os.chown(folder, OTHER_UID, OTHER_UID)
                else:
                    folder.chmod(0o555)
        return folder

    def _translate(self, value: str, mounts: dict[str, Path]) -> str:
        for path in sorted(mounts, key=len, reverse=True):
            if value == path or value.startswith(path.rstrip("/") + "/"):
                return str(mounts[path]) + value[len(path) :]
        return value

    # ------------------------------------------------------------ environment
    def _server_url(self, value: str) -> str:
        """A URL naming a compose server (``postgres:5432``) -> the machine's one."""
        try:
            host = urlsplit(value).hostname
        except ValueError:
            return value
        if host not in self.servers:
            return value
        real = self.servers[host]
        if value.startswith(("postgresql", "sqlite", "mysql")):
            mine, theirs = make_url(value), make_url(real)
            return mine.set(
                host=theirs.host,
                port=theirs.port,
                username=theirs.username,
                password=theirs.password,
                database=theirs.database,
            ).render_as_string(hide_password=False)
        theirs = urlsplit(real)
        return urlunsplit(urlsplit(value)._replace(netloc=theirs.netloc, path=theirs.path))

    def env(self, name: str) -> dict[str, str]:
        """The environment of service ``name``'s container."""
        mounts = self._mounts(name)
        home = self.image.homes.get(self.image.user or "") or "/"
        env = {
            "PATH": f"{self.built.python.bin}:{BASE_PATH}",
            "LANG": "C.UTF-8",
            "HOSTNAME": name,
            "HOME": self._translate(home, mounts),
        }
        for key, value in self.image.env.items():
            parts = value.split(":")
            env[key] = ":".join(self._translate(p, mounts) for p in parts)
        for key, value in environment(self.services[name]).items():
            env[key] = self._translate(self._server_url(value), mounts)
        env.update(self.extra_env.get(name, {}))
        return env

    def argv(self, name: str, command: list[str] | None = None) -> list[str]:
        """Service ``name``'s command as this machine runs it (paths, ports mapped)."""
        command = command or self.services[name].get("command") or self.image.cmd
        if isinstance(command, str):
            command = ["/bin/sh", "-c", command]
        mounts = self._mounts(name)
        out = []
        for word in command:
            if word == "0.0.0.0":
                word = "127.0.0.1"  # the container's every interface: here, loopback only
            elif word.isdigit() and int(word) in self.ports:
                word = str(self.ports[int(word)])
            out.append(self._translate(word, mounts))
        exe = shutil.which(out[0], path=self.env(name)["PATH"]) if "/" not in out[0] else out[0]
        assert exe, f"{name}: {out[0]!r} is not on the image's PATH"
        return [*(DROP_CAPS if self.as_root else []), exe, *out[1:]]

    def cwd(self, name: str) -> Path:
        workdir = self.services[name].get("working_dir") or self.image.workdir
        return Path(self._translate(workdir, self._mounts(name)))

    # ------------------------------------------------------------ processes
    def start(self, name: str) -> Child:
        log = self.logs / f"{name}.log"
        if log.exists():
            log.rename(self.logs / f"{name}.{len(list(self.logs.glob(name + '.*')))}.log")
        child = Child(name, self.argv(name), self.env(name), log=log, cwd=self.cwd(name))
        self.children[name] = child.start()
        return child

    def run(self, name: str, command: list[str], timeout: float = 120):
        """``docker compose run --rm NAME COMMAND``: a one-off container of ``name``."""
        return subprocess.run(
            self.argv(name, command),
            env=self.env(name),
            cwd=str(self.cwd(name)),
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )

    def up(self, names: list[str], timeout: float = 120) -> None:
        """Start ``names`` and what they depend on, each once its dependencies meet
        their ``condition`` (the machine's servers stand for postgres and redis)."""
        for name in self._order(names):
            for dep, spec in (self.services[name].get("depends_on") or {}).items():
                condition = (spec or {}).get("condition", "service_started")
                if dep not in self.ours:
                    continue
                if condition == "service_completed_successfully":
                    rc = self.wait_exit(dep, timeout)
                    assert rc == 0, f"{dep} exited {rc}:\n{self.tail(dep)}"
                elif condition == "service_healthy":
                    self.wait_healthy(dep, timeout)
            if name not in self.children:
                self.start(name)

    def _order(self, names: list[str]) -> list[str]:
        out: list[str] = []

        def visit(n: str, path: tuple[str, ...]) -> None:
            assert n not in path, f"depends_on circle: {' -> '.join((*path, n))}"
            if n in out or n not in self.ours:
                return
            for dep in self.services[n].get("depends_on") or {}:
                visit(dep, (*path, n))
            out.append(n)

        for n in names:
            visit(n, ())
        return out

    def down(self) -> None:
        stop_all(list(self.children.values()), grace=10)

    # ------------------------------------------------------------ waiting
    def healthy(self, name: str) -> bool:
        """The service's healthcheck ``test`` passes, run inside its container."""
        check = self.services[name]["healthcheck"]
        test = check["test"]
        if isinstance(test, str):
            test = ["CMD-SHELL", test]
        kind, rest = test[0], test[1:]
        assert kind in ("CMD", "CMD-SHELL"), f"{name}: healthcheck {kind} is not modelled"
        argv = rest if kind == "CMD" else ["/bin/sh", "-c", rest[0]]
        argv = [self._ports_in(w) for w in argv]
        try:
            proc = self.run(name, argv, timeout=seconds(check.get("timeout"), 30))
        except subprocess.TimeoutExpired:
            return False
        return proc.returncode == 0

    def _ports_in(self, text: str) -> str:
        for cport, hport in self.ports.items():
            text = re.sub(rf"(127\.0\.0\.1|localhost):{cport}\b", rf"\g<1>:{hport}", text)
        return text

    def wait_healthy(self, name: str, timeout: float = 120) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self._alive(name)
            if self.healthy(name):
                return
            time.sleep(0.5)
        raise AssertionError(f"{name} not healthy in {timeout}s:\n{self.tail(name)}")

    def wait_exit(self, name: str, timeout: float = 120) -> int:
        child = self.children[name]
        try:
            return child.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(
                f"{name} still running after {timeout}s:\n{self.tail(name)}"
            ) from None

    def wait_log(self, name: str, text: str, timeout: float = 120) -> str:
        deadline = time.monotonic() + timeout
        path = self.logs / f"{name}.log"
        while time.monotonic() < deadline:
            self._alive(name)
            log = path.read_text(errors="replace") if path.exists() else ""
            if text in log:
                return log
            time.sleep(0.2)
        raise AssertionError(f"{name}: {text!r} not logged in {timeout}s:\n{self.tail(name)}")

    def _alive(self, name: str) -> None:
        rc = self.children[name].poll()
        assert rc is None, f"{name} exited ({rc}):\n{self.tail(name)}"

    def tail(self, *names: str, n: int = 60) -> str:
        out = []
        for name in names or tuple(self.children):
            path = self.logs / f"{name}.log"
            lines = path.read_text(errors="replace").splitlines() if path.exists() else []
            out.append(f"--- {name} ---\n" + "\n".join(lines[-n:]))
        return "\n".join(out)
