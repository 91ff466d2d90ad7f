"""The house's size rules (docs/architecture.md): thin nodes, short module docstrings, one page of current results, no
path of one machine in a tracked file."""

from __future__ import annotations

import ast
from pathlib import Path
import subprocess

REPO = Path(__file__).resolve().parents[2]
MAX_NODE_LINES = 300
MAX_DOCSTRING_LINES, MAX_DOCSTRINGS_TOTAL = 30, 1200
MAX_RESULTS_LINES = 300


def tracked(pattern: str) -> list[Path]:
    out = subprocess.run(["git", "ls-files", pattern], cwd=REPO, capture_output=True, text=True, check=True).stdout
    return [REPO / line for line in out.split()]


def module_docstring_lines(path: Path) -> int:
    tree = ast.parse(path.read_text())
    if ast.get_docstring(tree) is None:
        return 0
    node = tree.body[0]
    return node.end_lineno - node.lineno + 1


def test_every_node_module_is_thin():
    nodes = [p for p in tracked("*.py") if p.stem.endswith("node") and p.parts[len(REPO.parts)].startswith("gsrmr_")]
    assert len(nodes) >= 5, nodes
    fat = {str(p.relative_to(REPO)): n for p in nodes if (n := len(p.read_text().splitlines())) > MAX_NODE_LINES}
    assert not fat, f"node modules over {MAX_NODE_LINES} lines: {fat}"


def test_module_docstrings_are_short():
    code = [p for p in tracked("*.py") if p.relative_to(REPO).parts[0] not in ("test", "bench", "docs")]
    lines = {str(p.relative_to(REPO)): module_docstring_lines(p) for p in code}
    long = {k: n for k, n in lines.items() if n > MAX_DOCSTRING_LINES}
    assert not long, f"module docstrings over {MAX_DOCSTRING_LINES} lines: {long}"
    assert sum(lines.values()) <= MAX_DOCSTRINGS_TOTAL, f"module docstrings: {sum(lines.values())} lines in all"


def test_results_are_one_page_and_no_machine_path_is_tracked():
    assert len((REPO / "docs" / "results.md").read_text().splitlines()) <= MAX_RESULTS_LINES
    assert (REPO / "CHANGELOG.md").is_file()
    machine_path = "/" + "work/"  # spelled in two parts so this file does not match itself
    found = subprocess.run(["git", "grep", "-l", machine_path], cwd=REPO, capture_output=True, text=True).stdout.split()
    assert found == [], f"a path of one machine in {found}"
