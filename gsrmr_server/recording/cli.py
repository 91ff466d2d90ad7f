"""``python -m gsrmr_server.recording {recover,info} PATH``: salvage a crashed run / summarise one.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from mcap.reader import make_reader

from gsrmr_server.recording.mcap_log import MCAP_NAME, recover_run
from gsrmr_server.recording.slots_csv import CSV_NAME, read_slots_csv


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m gsrmr_server.recording {recover,info} PATH``: salvage a crashed run / summarise one."""
    parser = argparse.ArgumentParser(prog="python -m gsrmr_server.recording", description=main.__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("recover", help="merge run-NNNN.mcap(.part) segments of a crashed run into run.mcap") \
        .add_argument("out_dir")
    sub.add_parser("info", help="messages per topic of an MCAP file and rows of slots.csv") \
        .add_argument("path", help="a run directory or an .mcap file")
    args = parser.parse_args(argv)
    if args.command == "recover":
        merged = recover_run(args.out_dir)
        print(f"recovered {merged}" if merged else f"nothing to recover in {args.out_dir}")
        return 0
    path = Path(args.path)
    mcap_path = path / MCAP_NAME if path.is_dir() else path
    with mcap_path.open("rb") as f:
        summary = make_reader(f).get_summary()
    if summary is None or summary.statistics is None:
        print(f"{mcap_path}: no summary section (unfinished file? try 'recover')")
        return 1
    stats = summary.statistics
    print(f"{mcap_path}: {stats.message_count} messages, log time "
          f"{stats.message_start_time / 1e9:.3f} … {stats.message_end_time / 1e9:.3f} s")
    for cid, channel in sorted(summary.channels.items(), key=lambda item: item[1].topic):
        schema = summary.schemas.get(channel.schema_id)
        print(f"  {channel.topic} [{schema.name if schema else '?'}]: "
              f"{stats.channel_message_counts.get(cid, 0)}")
    if path.is_dir() and (path / CSV_NAME).exists():
        print(f"{path / CSV_NAME}: {len(read_slots_csv(path / CSV_NAME))} slot rows")
    return 0
