"""The ``slots.csv`` codec: one row per slot, columns :data:`CSV_COLUMNS` (the fields of
:class:`gsrmr_server.slot_row.SlotRow`); exact float reprs, empty cell = not available.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import Any

from gsrmr_common.wire import RealSource
from gsrmr_server.slot_row import SLOT_ROW_COLUMNS

CSV_COLUMNS = SLOT_ROW_COLUMNS  # the fields of gsrmr_server.slot_row.SlotRow, in order
CSV_NAME = "slots.csv"
_INT_COLUMNS = frozenset({"slot", "x", "bytes_sent", "scored", "round_slot", "held_back", "scene_change",
                          "correction_seq"})
_STR_COLUMNS = frozenset({"source", "faults"})
SOURCES = tuple(s.value for s in RealSource)  # the source column: where r̂_t came from


def _cell(column: str, value: Any) -> str:
    """One CSV cell: '' for None/NaN, exact repr for floats, ';'-joined faults."""
    if value is None:
        return ""
    if column == "faults":
        if isinstance(value, str):
            return value
        return ";".join(str(v) for v in value)
    if column == "source":
        if value not in SOURCES:
            raise ValueError(f"slot row: source must be one of {SOURCES}, got {value!r}")
        return str(value)
    if column in _INT_COLUMNS:
        if isinstance(value, bool) or int(value) != value:
            raise ValueError(f"slot row: {column} must be an integer, got {value!r}")
        if column == "x" and value not in (0, 1):
            raise ValueError(f"slot row: x must be 0 (pose key) or 1 (image), got {value!r}")
        return str(int(value))
    number = float(value)
    return "" if math.isnan(number) else repr(number)


def _parse_cell(column: str, text: str) -> Any:
    if text == "":
        return None
    if column in _STR_COLUMNS:
        return text
    if column in _INT_COLUMNS:
        return int(text)
    return float(text)


def read_slots_csv(path: str | os.PathLike[str], columns: tuple[str, ...] = CSV_COLUMNS) -> list[dict[str, Any]]:
    """Rows of a ``slots.csv`` as dicts: ints for slot/x/bytes_sent, str for source/faults, float
    otherwise, ``None`` for empty cells. A last line without its newline (torn write) is dropped.
    ``columns``: the header the file must have (a file of some of these columns, e.g. the simulation's
    ``scores.csv``, is read with the same cell rules). A file whose header is the first of ``columns`` (one
    recorded before the last columns were added) reads with those cells ``None``."""
    with Path(path).open(newline="", encoding="utf-8") as f:
        text = f.read()
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    reader = csv.DictReader(text.splitlines(keepends=True))
    header = tuple(reader.fieldnames or ())
    if not header or header != columns[:len(header)]:
        raise ValueError(f"{path}: header {reader.fieldnames} is not {list(columns)}")
    return [{c: _parse_cell(c, row[c]) if c in header else None for c in columns} for row in reader]


def csv_line(row: dict[str, Any], columns: tuple[str, ...] = CSV_COLUMNS) -> str:
    """One CSV line (with its newline) of ``row``'s ``columns`` (missing = empty cell)."""
    return ",".join(_cell(c, row.get(c)) for c in columns) + "\n"


def write_slots_csv(path: str | os.PathLike[str], rows: list[dict[str, Any]]) -> None:
    """Write ``rows`` (dicts as :func:`read_slots_csv` returns them) as a ``slots.csv``."""
    with Path(path).open("w", newline="", encoding="utf-8") as f:
        f.write(",".join(CSV_COLUMNS) + "\n")
        for row in rows:
            f.write(csv_line(row))


def _json_value(value: Any) -> Any:
    return None if isinstance(value, float) and not math.isfinite(value) else value
