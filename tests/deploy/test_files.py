"""What the image holds and what the compose file says, without running anything:
every package pyproject's packages.find includes and every file pyproject and alembic
read is COPYed, nothing else is; the compose services have health checks, restart
policies, ordered start-up and the variables Settings reads (docs/deploy.md)."""

from __future__ import annotations

import configparser
import re
import subprocess
import tomllib
from pathlib import Path

import pytest
from setuptools import find_namespace_packages

from service.config import Settings
from tests.deploy import compose, dockerfile

ROOT = Path(__file__).resolve().parents[2]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
DOCS = (ROOT / "docs" / "deploy.md").read_text()
COMPOSE_TEXT = (ROOT / "docker-compose.yml").read_text()
SERVICES = compose.load(ROOT / "docker-compose.yml", {})["services"]
OURS = ("migrate", "api", "worker", "beat")


@pytest.fixture(scope="module")
def image():
    return dockerfile.parse(ROOT / "Dockerfile", ROOT)


def tracked(folder: str = "") -> list[str]:
    """The repository's files under ``folder`` (git's list; a folder walk without git)."""
    try:
        out = subprocess.run(
            ["git", "ls-files", "-z", "--", folder or "."],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        return sorted(p for p in out.split("\0") if p and (ROOT / p).is_file())
    except (OSError, subprocess.CalledProcessError):
        base = ROOT / folder
        return sorted(
            p.relative_to(ROOT).as_posix()
            for p in base.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts
        )


def packages() -> list[str]:
    find = PYPROJECT["tool"]["setuptools"]["packages"]["find"]
    found = find_namespace_packages(
        where=str(ROOT / find.get("where", ["."])[0]),
        include=find.get("include", ["*"]),
        exclude=find.get("exclude", []),
    )
    return sorted(found)


def in_image(image, path: str) -> bool:
    return f"{image.workdir.rstrip('/')}/{path}" in image.files


def test_every_package_pyproject_includes_is_copied_whole(image):
    names = packages()
    patterns = PYPROJECT["tool"]["setuptools"]["packages"]["find"]["include"]
    for pattern in patterns:  # each include pattern finds a package here
        assert any(re.fullmatch(pattern.replace("*", ".*"), n) for n in names), pattern
    for name in names:
        folder = name.replace(".", "/")
        files = [f for f in tracked(folder) if f.rsplit("/", 1)[0] == folder]
        missing = [f for f in files if not in_image(image, f)]
        assert not missing, f"package {name} is not COPYed whole (.dockerignore?): {missing}"


def test_every_file_pyproject_and_alembic_read_is_copied(image):
    needed = ["pyproject.toml"]
    project = PYPROJECT["project"]
    for key in ("readme", "license"):
        value = project.get(key)
        if isinstance(value, str) and key == "readme":
            needed.append(value)
        elif isinstance(value, dict) and "file" in value:
            needed.append(value["file"])
    ini = configparser.ConfigParser()
    ini.read(ROOT / "alembic.ini")
    scripts = ini.get("alembic", "script_location", raw=True).replace("%(here)s/", "")
    needed += ["alembic.ini", *tracked(scripts)]
    assert any(f.endswith("env.py") for f in tracked(scripts)), scripts
    missing = [f for f in needed if not in_image(image, f)]
    assert not missing, f"not in the image: {missing}"
    # service/db/migrate.py finds alembic.ini beside the folder of the `service` package
    assert in_image(image, "service/db/migrate.py") and in_image(image, "alembic.ini")


def test_the_image_holds_nothing_else(image):
    allowed = {"pyproject.toml", "alembic.ini"}
    scripts = ("migrations/",)
    folders = tuple(p.replace(".", "/") + "/" for p in packages())
    workdir = image.workdir.rstrip("/") + "/"
    extra = [
        p
        for p in image.files
        if not (
            p.startswith(workdir)
            and (p[len(workdir) :] in allowed or p[len(workdir) :].startswith(scripts + folders))
        )
    ]
    assert not extra, f"the image holds files it does not run: {extra[:20]}"
    assert not [p for p in image.files if "__pycache__" in p or p.endswith(".pyc")]


# ---------------------------------------------------------------- .dockerignore semantics

# Docker's documented examples (the .dockerignore section of the Dockerfile reference)
DOCKER_EXAMPLES = [
    ("*/temp*", "somedir/temporary.txt", True),
    ("*/temp*", "somedir/temp/file", True),
    ("*/temp*", "temporary.txt", False),
    ("*/*/temp*", "somedir/subdir/temporary.txt", True),
    ("*/*/temp*", "somedir/temporary.txt", False),
    ("temp?", "tempa", True),
    ("temp?", "tempab", False),
    ("**/*.go", "a/b/c.go", True),
    ("**/*.go", "c.go", True),
    ("*.md\n!README.md", "README.md", False),
    ("*.md\n!README.md", "CHANGES.md", True),
    ("*.md\n!README*.md\nREADME-secret.md", "README-secret.md", True),
    ("*.md\n!README*.md\nREADME-secret.md", "README-public.md", False),
]


@pytest.mark.parametrize("rules,path,out", DOCKER_EXAMPLES)
def test_dockerignore_rules_as_docker_documents_them(rules, path, out):
    assert dockerfile.excluded(dockerfile.ignore_rules(rules), path) is out


def test_copy_as_docker_documents_it(tmp_path):
    # a folder's contents are copied, not the folder; several sources go into a folder;
    # a wildcard matches within one path segment
    for path in ("pkg/a.py", "pkg/sub/b.py", "one.toml", "two.ini", "pkg2/c.py", "x/pkg3/d.py"):
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text("")
    (tmp_path / "Dockerfile").write_text(
        "FROM python:3.11-slim\nWORKDIR /app\nCOPY pkg ./pkg\nCOPY one.toml two.ini ./\n"
        "COPY pkg2 /opt/\nCOPY one.toml /etc/renamed.toml\nCOPY pkg* /wild/\n"
    )
    files = dockerfile.parse(tmp_path / "Dockerfile", tmp_path).files
    assert files == {
        "/app/pkg/a.py": "pkg/a.py",
        "/app/pkg/sub/b.py": "pkg/sub/b.py",
        "/app/one.toml": "one.toml",
        "/app/two.ini": "two.ini",
        "/opt/c.py": "pkg2/c.py",
        "/etc/renamed.toml": "one.toml",
        "/wild/a.py": "pkg/a.py",
        "/wild/sub/b.py": "pkg/sub/b.py",
        "/wild/c.py": "pkg2/c.py",
    }


def test_a_run_command_the_model_does_not_know_fails_the_parse(tmp_path):
    (tmp_path / "Dockerfile").write_text("FROM python:3.11-slim\nRUN apt-get update\n")
    with pytest.raises(dockerfile.Unsupported, match="apt-get"):
        dockerfile.parse(tmp_path / "Dockerfile", tmp_path)


# ---------------------------------------------------------------- docker-compose.yml


def test_every_service_of_the_image_is_built_from_this_dockerfile():
    built = sorted(n for n, s in SERVICES.items() if "build" in s)
    assert built == sorted(OURS)
    for name in OURS:
        build = SERVICES[name]["build"]
        context = build if isinstance(build, str) else build.get("context", ".")
        assert context == "." and build.get("dockerfile", "Dockerfile") == "Dockerfile"


def test_health_checks():
    def test_of(name):
        t = SERVICES[name]["healthcheck"]["test"]
        return " ".join(t) if isinstance(t, list) else t

    assert "pg_isready" in test_of("postgres")
    assert re.search(r"redis-cli\b.*\bping", test_of("redis"))
    assert re.search(r"127\.0\.0\.1:8000/(healthz|readyz)\b", test_of("api"))


def test_restart_policies_and_start_order():
    for name, service in SERVICES.items():
        policy = service.get("restart")
        if name == "migrate":
            assert policy in ("no", "on-failure"), policy  # a one-off: never looped forever
        else:
            assert policy in ("unless-stopped", "always"), (name, policy)
    assert SERVICES["migrate"]["depends_on"] == {"postgres": {"condition": "service_healthy"}}
    for name in ("api", "worker", "beat"):
        assert SERVICES[name]["depends_on"] == {
            "postgres": {"condition": "service_healthy"},
            "redis": {"condition": "service_healthy"},
            "migrate": {"condition": "service_completed_successfully"},
        }
    assert SERVICES["beat"]["deploy"]["replicas"] == 1


def test_the_scaling_line_is_documented():
    for text in (COMPOSE_TEXT, DOCS):
        assert "docker compose up -d --scale worker=4" in text


def test_the_database_url_names_the_postgres_service_account():
    from sqlalchemy.engine import make_url

    pg = compose.environment(SERVICES["postgres"])
    for name in OURS:
        env = compose.environment(SERVICES[name])
        url = make_url(env["SVROBS_DATABASE_URL"])
        assert (url.host, url.username, url.password, url.database) == (
            "postgres",
            pg["POSTGRES_USER"],
            pg["POSTGRES_PASSWORD"],
            pg["POSTGRES_DB"],
        )
        assert env["SVROBS_BROKER_URL"].startswith("redis://redis:")


SETTINGS = {f"SVROBS_{name}" for name in Settings.model_fields}


def test_every_svrobs_variable_the_image_and_compose_set_is_a_setting(image):
    # Settings ignores unknown names: a misspelt variable would change nothing, silently
    names = {k for k in image.env if k.startswith("SVROBS_")}
    for name in OURS:
        names |= {k for k in compose.environment(SERVICES[name]) if k.startswith("SVROBS_")}
    assert names and names <= SETTINGS, sorted(names - SETTINGS)


def test_docs_list_every_setting_and_no_other_variable():
    client_vars = set()
    for path in (ROOT / "svrobs_client").rglob("*.py"):
        client_vars |= set(re.findall(r"\"(SVROBS_\w+)\"", path.read_text()))
    named = set(re.findall(r"`(SVROBS_[A-Z0-9_]+)`", DOCS))
    operator = {s for s in SETTINGS if not s.startswith("SVROBS_TEST_")}
    assert not operator - named, f"docs/deploy.md does not list {sorted(operator - named)}"
    unknown = named - SETTINGS - client_vars
    assert not unknown, f"docs/deploy.md names variables nothing reads: {sorted(unknown)}"
