"""README is the user's map: what it says about the launch files and the wire layouts is read back from the code.

The launch arguments come from the launch files themselves (their ``DeclareLaunchArgument`` calls, read with
``ast``: no ROS tooling needed), the layouts from :mod:`gsrmr_common.wire`. A changed argument, default or field
that README does not follow fails here, and so does a ``wire.py`` docstring that leaves a field out.
"""

from __future__ import annotations

import ast
from pathlib import Path
import re

import pytest

from gsrmr_common import wire
from gsrmr_common.ros_wire import SCHEDULE_LABELS

REPO = Path(__file__).resolve().parents[2]
README = (REPO / "README.md").read_text()
REQUIRED = "required"
NOT_A_LITERAL = object()


def table_rows(first_cell: str) -> dict[str, list[str]]:
    """README table rows whose first cell matches ``first_cell`` (a regex), keyed by that cell's text."""
    rows = {}
    for line in README.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and re.fullmatch(first_cell, cells[0]):
            rows[cells[0]] = cells
    return rows


def declared_arguments(path: Path) -> dict[str, object]:
    """name → default (a string; :data:`REQUIRED` without one; :data:`NOT_A_LITERAL` for a computed one)."""
    out: dict[str, object] = {}
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", "")) == \
                "DeclareLaunchArgument":
            name = node.args[0].value  # type: ignore[attr-defined]
            default = next((k.value for k in node.keywords if k.arg == "default_value"), None)
            if default is None:
                out[name] = REQUIRED
            elif isinstance(default, ast.Constant):
                out[name] = default.value
            else:
                out[name] = NOT_A_LITERAL
    return out


def readme_arguments(cell: str) -> dict[str, str]:
    """``\\`name\\` (default)`` entries of a README cell → name → default as written (backticks removed)."""
    return {m.group(1): m.group(2).strip().strip("`") for m in re.finditer(r"`([a-z_]+)` \(([^)]*)\)", cell)}


LAUNCH_FILES = sorted((REPO / "launch").glob("*.launch.py"))


def test_readme_stays_a_map():
    assert len(README.splitlines()) <= 220
    assert "arXiv:2504.13697" in README  # the paper, for a reader who cloned the repository alone
    assert "GSRMR_ROS_TOOLING" in README  # where ros2 launch / launch_testing come from without a ROS install
    assert "docs/results.md" in README


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=[p.name for p in LAUNCH_FILES])
def test_readme_launch_arguments_are_the_launch_files(path: Path):
    rows = table_rows(r"`[a-z_]+\.launch\.py`")
    assert f"`{path.name}`" in rows, f"README's launch table has no row for {path.name}"
    documented = readme_arguments(rows[f"`{path.name}`"][-1])
    declared = declared_arguments(path)
    assert declared, f"{path.name} declares no argument?"
    assert list(documented) == list(declared), f"{path.name}: README lists {list(documented)}, the file declares " \
                                               f"{list(declared)} (same order as --show-args)"
    for name, default in declared.items():
        if default is NOT_A_LITERAL:  # computed (e.g. a path in the package's share folder): described, not quoted
            assert documented[name], name
        else:
            assert documented[name] == default, f"{path.name} {name}: README says {documented[name]!r}, " \
                                                f"the file {default!r}"


def layout(record: str) -> str:
    rows = table_rows(re.escape(record))
    assert record in rows, f"README's wire table has no row {record!r}"
    return rows[record][-1]


def listed(cell: str) -> list[str]:
    """The names of the first ``[a, b, …]`` list in a README cell."""
    match = re.search(r"\[([^\]]*)\]", cell)
    assert match, cell
    return [name.strip() for name in match.group(1).split(",")]


@pytest.mark.parametrize(("record", "fields"), [
    ("ledger row", wire.LEDGER_FIELDS),
    ("loss sample", wire.LOSS_SAMPLE_FIELDS),
    ("channel sample", wire.CHANNEL_SAMPLE_FIELDS),
    ("MR slot info", wire.MR_SLOT_INFO_FIELDS),
])
def test_readme_wire_layouts_are_wire_py(record: str, fields: tuple[str, ...]):
    assert listed(layout(record)) == list(fields)


def test_readme_schedule_pose_key_and_image_layouts():
    schedule = layout("schedule")
    assert listed(schedule) == list(wire.SCHEDULE_META)
    blocks = re.findall(r"`([a-z_]+)\[slots\]`", schedule)
    assert blocks == [*SCHEDULE_LABELS[1:], "gain_threshold"]
    key = layout("pose key")
    assert f"`{wire.MAP_FRAME}`" in key and f"({wire.POSE_KEY_BITS} bits)" in key
    assert f"`{wire.JPEG_FORMAT}`" in layout("image")
    topics = {"MR slot info": wire.MR_SLOT_INFO_TOPIC, "channel sample": wire.CHANNEL_TOPIC}
    for record, topic in topics.items():
        assert table_rows(re.escape(record))[record][1] == f"`{topic}`"


def test_wire_py_docstring_names_every_field():
    doc = wire.__doc__ or ""
    names = {*wire.LEDGER_FIELDS, *wire.LOSS_SAMPLE_FIELDS, *wire.CHANNEL_SAMPLE_FIELDS, *wire.MR_SLOT_INFO_FIELDS,
             *wire.SCHEDULE_META, *SCHEDULE_LABELS, "gain_threshold"}
    missing = sorted(n for n in names if not re.search(rf"\b{n}\b", doc))
    assert not missing, f"gsrmr_common/wire.py's docstring leaves out {missing}"


def test_the_checks_catch_drift():
    """The parsers above find what they must: a README cell with a renamed argument and a ledger list without
    a field do not pass for the real ones."""
    assert readme_arguments("`port` (`/dev/x`), `jpeg_quality` (`80`)") == {"port": "/dev/x", "jpeg_quality": "80"}
    assert listed("`[slot, x]` (…)") == ["slot", "x"] != list(wire.LEDGER_FIELDS)
    server = declared_arguments(REPO / "launch" / "server.launch.py")
    assert server["model_path"] == REQUIRED and server["loss_threshold"] == "0.03"
    assert server["route_file"] is NOT_A_LITERAL
