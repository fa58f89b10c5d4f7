"""The project's files speak of the project: its dates, versions, commits and criteria, not of
the work that made them.  Every tracked text file is read for words of that kind."""

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# built from parts so that this file does not match itself
WORDS = re.compile(r"\b(" + "|".join([
    "sess" + r"ions?",              # a work period, numbered
    "le" + "nt",                    # a machine on loan
    "device " + r"calls?",
    "carr" + r"(y|ies|ied)",        # what such a call may hold
    "iss" + r"ues? #?\d+",          # a tracker's number: state the criterion instead
]) + r")\b", re.IGNORECASE)
# the names other libraries give to their own things
ALLOWED = [re.compile(p) for p in (
    r"""scope=["']sess""" + r"""ion["']""",  # pytest's fixture scope
    r"Ray sess" + "ion",            # a Ray cluster connection (ray.init)
)]
TEXT = {".py", ".md", ".toml", ".cfg", ".txt", ".xml", ".json", ".yaml", ".yml", ".sh", ".cff", ""}


def _tracked_text_files() -> list[Path]:
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z"], capture_output=True,
                             check=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        pytest.skip("not a git checkout")
    paths = [ROOT / p for p in out.decode().split("\0") if p]
    return [p for p in paths if p.is_file() and p.suffix in TEXT and p.stat().st_size < 5_000_000]


def _hits(text: str) -> list[str]:
    hits = []
    for number, line in enumerate(text.splitlines(), 1):
        rest = line
        for allowed in ALLOWED:
            rest = allowed.sub("", rest)
        if WORDS.search(rest):
            hits.append(f"{number}: {line.strip()[:120]}")
    return hits


def test_the_pattern_finds_what_it_is_for():
    assert _hits("the default before sess" + "ion 19") and _hits("see iss" + "ue 18")
    assert _hits("a call can car" + "ry 64 MiB") and _hits("no GPU was le" + "nt")
    assert not _hits('@pytest.fixture(scope="sess' + 'ion")') and not _hits("no Ray sess" + "ion yet")
    assert not _hits("the excellent silent talent") and not _hits("carrying")


def test_no_tracked_file_speaks_of_how_it_was_made():
    found = {}
    for path in _tracked_text_files():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        if hits := _hits(text):
            found[str(path.relative_to(ROOT))] = hits[:5]
    assert not found, "words of the work, not of the project:\n" + "\n".join(
        f"{p}: {h}" for p, hs in found.items() for h in hs)
