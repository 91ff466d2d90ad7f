"""The console scripts setup.py declares, read from setup.py itself (no install needed), shared by the launch-file
tests and the fleet tests."""

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def console_scripts() -> set[str]:
    tree = ast.parse((REPO / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "CONSOLE_SCRIPTS" for t in node.targets):
            return {ast.literal_eval(e).split("=")[0].strip() for e in node.value.elts}
    raise AssertionError("CONSOLE_SCRIPTS not found in setup.py")
