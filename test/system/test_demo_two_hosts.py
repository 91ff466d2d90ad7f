"""``gsrmr-demo --hosts 2`` itself (root only): interrupted mid-round with Ctrl-C, it removes everything it made.

A tiny model (12 round-1 frames, 30 training steps, uncompacted) and a 50-slot round (its survey, before round 2,
takes about 0.16 s a slot: 16 s of the test at 100 slots) keep this to about half a minute; the demo is interrupted
(SIGINT, as a terminal's Ctrl-C) once round 2 runs. Afterwards no namespace of its, no veth, no process of its ROS
domain and no truth-frame folder may be left.
"""

from __future__ import annotations

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import pytest

from gsrmr_sim.netns import NETNS_PREFIX, namespaces, unavailable_reason

pytestmark = [pytest.mark.ros, pytest.mark.slow,
              pytest.mark.skipif(unavailable_reason() is not None, reason=f"two hosts: {unavailable_reason()}")]


#: Round 2's slots: 5 s of real time, its Ctrl-C comes within about 0.5 s of the round's start line
ROUND_SLOTS = 50


def _gsrmr_processes(marker: str) -> list[str]:
    """Command lines of running processes that mention ``marker`` (the demo's output folder)."""
    found = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if marker in cmd:
            found.append(cmd)
    return found


def test_ctrl_c_mid_round_removes_namespaces_links_and_processes(tmp_path):
    out = tmp_path / "report"
    before = {ns for ns in namespaces() if ns.startswith(NETNS_PREFIX)}
    exe = Path(sys.executable).parent / "gsrmr-demo"
    log = (tmp_path / "demo.log").open("w")
    proc = subprocess.Popen([str(exe), "--hosts", "2", "--uplink-mbit", "2", "--frames", "12", "--train-iterations",
                             "30", "--train-width", "80", "--no-compact", "--slots", str(ROUND_SLOTS), "--cache",
                             str(tmp_path / "cache"), "--out", str(out)],
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 240
        text = ""
        while time.monotonic() < deadline and proc.poll() is None:
            text = (tmp_path / "demo.log").read_text()
            if "round 2: " in text and f"/{ROUND_SLOTS} slots" in text:
                break
            time.sleep(0.5)
        assert proc.poll() is None, text[-3000:]
        assert "two hosts: robot" in text, text[-3000:]
        ours = {ns for ns in namespaces() if ns.startswith(NETNS_PREFIX)} - before
        assert len(ours) == 2  # robot and server
        assert _gsrmr_processes(str(out))  # the nodes run (their parameter files live in the report folder)
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in the demo's terminal
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        log.close()
    assert not ({ns for ns in namespaces() if ns.startswith(NETNS_PREFIX)} - before)
    assert not _gsrmr_processes(str(out))
    assert not (out / "truth_frames").exists()
    links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True).stdout
    assert not [line for line in links.splitlines() if any(ns[len(NETNS_PREFIX):-1] in line for ns in ours)]
