"""The documentation stands alone: every link resolves, nothing cites a file users lack.

* Every Markdown link (``[text](target)``, ``![alt](target)``) in ``README.md``,
  ``CONTRIBUTING.md`` and ``docs/**/*.md`` points at a file of the repository, and
  its ``#anchor`` at a heading of that file (GitHub's anchors: lower case,
  punctuation dropped, spaces to hyphens, ``-1``, ``-2`` for repeated headings) or
  at an explicit ``<a id="...">``; every repository path they name in backticks
  (```svrobs_core/spec.py```) exists.
* Every ``docs/<file>.md#anchor`` written in code (Python, templates, scripts,
  styles, configuration) names an existing file and anchor.
* No file cites the shared texts the docs replace (``SPEC.md``, ``DESIGN.md``,
  "SPEC section N"), and no file tells history instead of what is (the words of
  ``HISTORY``), outside the short allow-list below.

The oracle is the files themselves: the anchors are computed from the headings
by GitHub's rule, independently of how the links were written.
"""

from __future__ import annotations

import re
import subprocess
import unicodedata
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# what is checked for a citation of the shared specification and for history
TEXT_SUFFIXES = {".py", ".md", ".html", ".js", ".css", ".toml", ".yml", ".yaml", ".cfg", ".ini"}
TEXT_NAMES = {"Makefile", "Dockerfile", "run"}

SPEC_CITATION = re.compile(
    r"SPEC\.md|DESIGN\.md"
    r"|\bSPEC(?:'s)?\s+(?:sections?|§|\d|[Dd]ecision|literally|default)"
    r"|\b(?:[Tt]he|a|our|of) SPEC\b"
    r"|\bsections? 10(?![.\d])"
)
SPEC_WORD = re.compile(r"\bSPEC\b")  # in Markdown, any mention
HISTORY = re.compile(
    r"this session|previous session|(?:first|second|earlier|last) session"
    r"|\bissues? \d+|\bwaves?\b",
    re.IGNORECASE,
)
# (path, the matched text): legitimate uses of a HISTORY word
HISTORY_ALLOWED = {
    ("tests/web/test_session.py", "this session"),  # a web session's CSRF token
    ("service/web/deps.py", "this session"),
}

MD_LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
CODE_DOC_REF = re.compile(r"(?<![\w/.-])docs/([\w./-]+?\.md)(#[\w-]+)?")
EXPLICIT_ANCHOR = re.compile(r"<a\s+(?:id|name)=\"([^\"]+)\"")
FENCE = re.compile(r"^\s*(```|~~~)")
# a path of the repository written in backticks: `svrobs_core/spec.py`, `tests/faults/`
REPO_PATH = re.compile(
    r"`((?:service|svrobs_core|svrobs_lab|svrobs_cli|svrobs_client|worker|tests|bench|"
    r"migrations|docs)/[\w./-]*?(?:\.(?:py|md|js|css|html|png|toml)|/))`"
)


def tracked_files() -> list[Path]:
    out = subprocess.run(
        ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout
    files = [ROOT / p for p in out.split("\0") if p]
    # files added in the working tree but not yet committed count too
    extra = subprocess.run(
        ["git", "ls-files", "-z", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    files += [ROOT / p for p in extra.split("\0") if p]
    return sorted({f for f in files if f.is_file()})


def text_files() -> list[Path]:
    return [
        f
        for f in tracked_files()
        if (f.suffix in TEXT_SUFFIXES or f.name in TEXT_NAMES) and "vendor" not in f.parts
    ]


def markdown_files() -> list[Path]:
    docs = sorted((ROOT / "docs").rglob("*.md"))
    return [ROOT / "README.md", ROOT / "CONTRIBUTING.md", *docs]


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a heading (github-slugger's rule)."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link keeps its text
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML
    text = text.strip().lower()
    kept = []
    for ch in text:
        cat = unicodedata.category(ch)
        if ch in " -_" or cat[0] in "LNM":
            kept.append(ch)
    return "".join(kept).replace(" ", "-")


def _outside_fences(text: str) -> list[str]:
    lines, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            lines.append("")
            continue
        lines.append("" if fenced else line)
    return lines


@cache
def anchors(path: Path) -> frozenset[str]:
    """Every anchor a link into ``path`` may use."""
    text = path.read_text(encoding="utf-8")
    seen: dict[str, int] = {}
    out = set(EXPLICIT_ANCHOR.findall(text))
    for line in _outside_fences(text):
        m = re.match(r"^(#{1,6})\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        slug = github_slug(m.group(2))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return frozenset(out)


def _check_target(source: Path, target: str) -> str | None:
    """None if ``target`` (a link written in ``source``) resolves, else why not."""
    if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("//"):
        return None  # another host (http:, https:, mailto:)
    path_part, _, anchor = target.partition("#")
    if path_part.startswith("/"):
        return f"{target}: an absolute path, not a file of the repository"
    dest = (source.parent / path_part).resolve() if path_part else source
    if not dest.exists():
        return f"{target}: no file {dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest}"
    if anchor:
        if dest.suffix != ".md":
            return f"{target}: an anchor into a file that is not Markdown"
        if anchor not in anchors(dest):
            return f"{target}: no heading with anchor #{anchor} in {dest.relative_to(ROOT)}"
    return None


def test_github_slug_rule():
    # GitHub's anchors of headings of these docs, as GitHub shows them
    assert github_slug("3.7 Caveats: the paper's bounds do not hold as stated") == (
        "37-caveats-the-papers-bounds-do-not-hold-as-stated"
    )
    assert github_slug("8. SLS sub-optimal observer (J_opt)") == "8-sls-sub-optimal-observer-j_opt"
    assert github_slug("Stage `cost_bound`") == "stage-cost_bound"
    assert github_slug('σ_w = "estimate": an upper bound') == "σ_w--estimate-an-upper-bound"
    assert github_slug("(e) The parametric bootstrap (Dean, Mania 2020, Alg. 2)") == (
        "e-the-parametric-bootstrap-dean-mania-2020-alg-2"
    )


def test_the_checker_finds_a_broken_link(tmp_path):
    # the check can fail: a missing file and a missing anchor are both reported
    page = ROOT / "docs" / "spec.md"
    assert _check_target(page, "science.md#no-such-heading") is not None
    assert _check_target(page, "no-such-file.md") is not None
    assert _check_target(page, "science.md#2-estimators") is None
    assert _check_target(page, "#spec-fields") is None
    assert SPEC_CITATION.search("as SPEC section 3 says")
    assert SPEC_CITATION.search("see SPEC.md")
    assert SPEC_CITATION.search("one section 10 record per line")
    assert not SPEC_CITATION.search("SMALL_SPEC = {} and section 10.2")
    assert HISTORY.search("measured in this session")
    assert HISTORY.search("as issue 12 asked")
    assert SPEC_CITATION.search("changes from DESIGN.md")
    assert REPO_PATH.findall("see `svrobs_core/spec.py` and `tests/faults/`") == [
        "svrobs_core/spec.py",
        "tests/faults/",
    ]


@pytest.mark.parametrize("md", markdown_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_markdown_links_resolve(md):
    broken = []
    for lineno, line in enumerate(_outside_fences(md.read_text(encoding="utf-8")), 1):
        for target in MD_LINK.findall(line):
            why = _check_target(md, target)
            if why:
                broken.append(f"{md.relative_to(ROOT)}:{lineno}: {why}")
    assert not broken, "\n".join(broken)


@pytest.mark.parametrize("md", markdown_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_paths_named_in_docs_exist(md):
    missing = []
    for lineno, line in enumerate(md.read_text(encoding="utf-8").splitlines(), 1):
        for path in REPO_PATH.findall(line):
            if not (ROOT / path).exists():
                missing.append(f"{md.relative_to(ROOT)}:{lineno}: {path}")
    assert not missing, "\n".join(missing)


def test_docs_references_in_code_resolve():
    broken = []
    for f in text_files():
        if f.suffix == ".md" and f.parent == ROOT / "docs":
            continue  # links inside docs/ are relative and checked above
        for lineno, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1):
            for m in CODE_DOC_REF.finditer(line):
                why = _check_target(ROOT / "README.md", "docs/" + m.group(1) + (m.group(2) or ""))
                if why:
                    broken.append(f"{f.relative_to(ROOT)}:{lineno}: {why}")
    assert not broken, "\n".join(broken)


def test_nothing_cites_the_shared_spec():
    found = []
    for f in text_files():
        if f == Path(__file__):
            continue
        for lineno, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1):
            m = SPEC_CITATION.search(line) or (f.suffix == ".md" and SPEC_WORD.search(line))
            if m:
                found.append(f"{f.relative_to(ROOT)}:{lineno}: {m.group(0)!r}: {line.strip()}")
    assert not found, "cite docs/<file>.md#anchor instead:\n" + "\n".join(found)


def test_no_words_of_history():
    found = []
    for f in text_files():
        rel = str(f.relative_to(ROOT))
        if f == Path(__file__):
            continue
        for lineno, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1):
            for m in HISTORY.finditer(line):
                if (rel, m.group(0).lower()) in HISTORY_ALLOWED:
                    continue
                found.append(f"{rel}:{lineno}: {m.group(0)!r}: {line.strip()}")
    assert not found, "say what is, not how it came:\n" + "\n".join(found)
