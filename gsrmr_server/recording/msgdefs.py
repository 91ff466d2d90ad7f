"""ROS 2 message definitions in the rosbag2 ``ros2msg`` encoding, generated from the installed ``.msg``
files: the top-level definition, then each nested type after a line of 80 ``=`` and ``MSG: pkg/msg/Type``.
"""

from __future__ import annotations

from collections.abc import Sequence
import contextlib
import importlib
import os
from pathlib import Path
import re
import sys

_PRIMITIVES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
                         "int32", "uint32", "int64", "uint64", "string", "wstring"})
_SEPARATOR = "=" * 80


def _msg_file(package: str, name: str) -> Path:
    """Locate ``<prefix>/share/<package>/msg/<name>.msg`` of an installed interface package."""
    prefixes = [Path(sys.prefix)]
    prefixes += [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    with contextlib.suppress(ImportError, TypeError):
        module_file = importlib.import_module(package).__file__
        if module_file is not None:  # <prefix>/lib/pythonX.Y/site-packages/<package>/__init__.py
            prefixes.append(Path(module_file).resolve().parents[4])
    for prefix in prefixes:
        candidate = prefix / "share" / package / "msg" / f"{name}.msg"
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(f"{package}/msg/{name}.msg not found under {[str(p) for p in prefixes]}")


def _strip_comments(text: str) -> list[str]:
    """Definition lines without comments and blank lines (string constants keep a literal '#')."""
    lines = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        first = line.split()[0]
        if "#" in line and not (first.startswith(("string", "wstring")) and "=" in line.split("#")[0]):
            line = line.split("#", 1)[0].rstrip()
        lines.append(line)
    return lines


def _field_dependencies(package: str, lines: Sequence[str]) -> list[str]:
    """Nested message types (``pkg/msg/Type``) used by the fields of a definition."""
    deps = []
    for line in lines:
        parts = line.split()
        if len(parts) < 2 or "=" in parts[1] or (len(parts) > 2 and parts[2].startswith("=")):
            continue  # constants are always primitive
        base = re.sub(r"\[.*\]$", "", parts[0])
        base = re.sub(r"<=\d+$", "", base)
        if base in _PRIMITIVES:
            continue
        pieces = base.split("/")
        pkg, name = (pieces[0], pieces[-1]) if len(pieces) > 1 else (package, pieces[0])
        deps.append(f"{pkg}/msg/{name}")
    return deps


def message_definition(type_name: str) -> str:
    """Complete ``ros2msg`` definition of ``pkg/msg/Type`` from the installed ``.msg`` files.

    The top-level definition comes first; every nested type follows once, after a line of 80 ``=`` and
    ``MSG: pkg/msg/Type`` (rosbag2's encoding, read by Foxglove and mcap-ros2-support).
    Comments are stripped.
    """
    pieces = type_name.split("/")
    if len(pieces) not in (2, 3):
        raise ValueError(f"message type must look like pkg/msg/Type, got {type_name!r}")
    order: list[str] = []
    texts: dict[str, str] = {}

    def visit(full: str) -> None:
        if full in texts:
            return
        pkg, _, name = full.split("/")
        lines = _strip_comments(_msg_file(pkg, name).read_text())
        texts[full] = "\n".join(lines)
        order.append(full)
        for dep in _field_dependencies(pkg, lines):
            visit(dep)

    visit(f"{pieces[0]}/msg/{pieces[-1]}")
    out = [texts[order[0]]]
    for dep in order[1:]:
        out.append(f"{_SEPARATOR}\nMSG: {dep}\n{texts[dep]}")
    return "\n".join(out) + "\n"
