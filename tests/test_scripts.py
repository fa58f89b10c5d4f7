"""The scripts beside the library (``experiments/``, ``benchmarks/``, ``research/``, ``tools/``)
run from the installed package: none edits ``sys.path`` and none imports another script, so
what two scripts share lives in the library (``f2f_jax.bench``, ``f2f_jax.tables``)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("experiments", "benchmarks", "research", "tools")
SCRIPTS = sorted(p for folder in FOLDERS for p in (ROOT / folder).glob("*.py"))
NAMES = {p.stem for p in SCRIPTS}


def _problems(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr == "path" and \
                isinstance(node.value, ast.Name) and node.value.id == "sys":
            bad.append(f"line {node.lineno}: sys.path")
        modules = []
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level:
            modules = [node.module or ""]
        elif isinstance(node, ast.ImportFrom):
            modules = ["." + (node.module or "")]
        for module in modules:
            top = module.split(".")[0]
            if module.startswith(".") or top in FOLDERS or top in NAMES:
                bad.append(f"line {node.lineno}: imports the script {module}")
    return bad


def test_there_are_scripts_in_every_folder():
    assert {p.parent.name for p in SCRIPTS} == set(FOLDERS)


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_a_script_edits_no_path_and_imports_no_other_script(path):
    assert not _problems(path), "\n".join(_problems(path))


def test_the_check_sees_both(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("import sys\nsys.path.insert(0, '..')\nfrom protocol_fidelity import run_peer\n")
    assert len(_problems(probe)) == 2
