"""Ctrl-C ends a node with exit code 0 in every phase (gsrmr_common.interrupts), tested on real processes.

A stand-in node module (slow import, a spin loop, a slow clean-up) runs under ``node_entry`` in a child
process; the test sends SIGINT at the moment it wants, as a terminal and ``ros2 launch`` do.
"""

from __future__ import annotations

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import pytest

from gsrmr_common.interrupts import CLEANUP, RUNNING, START, InterruptPolicy

STAND_IN = '''
import os, sys, time
print("importing", flush=True)
try:
    time.sleep(float(os.environ.get("IMPORT_S", "0")))
except KeyboardInterrupt:
    if os.environ.get("CONVERT"):  # what a C extension's callback may do with an interrupt
        raise RuntimeError("interrupted inside an extension") from None
    raise
if os.environ.get("FAIL"):
    raise RuntimeError("a real start-up error")

def main():
    from gsrmr_common.interrupts import CLEANUP, POLICY, RUNNING
    POLICY.enter(RUNNING)
    print("running", flush=True)
    while not POLICY.stop_requested:  # as run_node's spin loop: nothing is raised while running
        time.sleep(0.02)
    POLICY.enter(CLEANUP)
    print("cleanup", flush=True)
    time.sleep(1.0)
    print("done", flush=True)
    return 0
'''


def start(tmp_path: Path, import_s: float, **flags: str) -> subprocess.Popen:
    (tmp_path / "stand_in_node.py").write_text(STAND_IN)
    code = "import sys; from gsrmr_common.interrupts import node_entry; sys.exit(node_entry('stand_in_node:main')())"
    env = dict(os.environ, IMPORT_S=str(import_s), **flags,
               PYTHONPATH=os.pathsep.join([str(tmp_path), *sys.path]))
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)


def wait_line(proc: subprocess.Popen, text: str, timeout_s: float = 20.0) -> list[str]:
    lines, deadline = [], time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        lines.append(line.strip())
        if text in line:
            return lines
        if not line:
            break
    pytest.fail(f"{text!r} not printed: {lines}")


def test_sigint_during_the_import_exits_zero(tmp_path):
    proc = start(tmp_path, import_s=30.0)
    wait_line(proc, "importing")
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0 and "running" not in out


def test_interrupt_turned_into_another_exception_still_exits_zero(tmp_path):
    proc = start(tmp_path, import_s=30.0, CONVERT="1")
    wait_line(proc, "importing")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0 and "stopped by a signal" in err, err


def test_a_real_error_without_a_signal_still_fails(tmp_path):
    proc = start(tmp_path, import_s=0.0, FAIL="1")
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 1 and "a real start-up error" in err, err


def test_second_sigint_does_not_cut_the_cleanup_short(tmp_path):
    proc = start(tmp_path, import_s=0.0)
    wait_line(proc, "running")
    proc.send_signal(signal.SIGINT)  # the terminal's
    wait_line(proc, "cleanup")
    proc.send_signal(signal.SIGINT)  # launch's, while the node cleans up
    out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0 and "done" in out, out


def test_policy_phases():
    policy = InterruptPolicy()
    policy.enter(START)
    with pytest.raises(KeyboardInterrupt):
        policy._handle(signal.SIGINT, None)
    policy.enter(RUNNING)
    assert not policy.stop_requested
    policy._handle(signal.SIGINT, None)  # no exception inside the executor: the spin loop stops
    assert policy.stop_requested
    policy.enter(CLEANUP)
    policy._handle(signal.SIGINT, None)
    policy._handle(signal.SIGTERM, None)
    with pytest.raises(KeyboardInterrupt):  # a third signal: the user insists
        policy._handle(signal.SIGINT, None)
    with pytest.raises(ValueError):
        policy.enter("later")


def test_start_up_signal_inside_a_finalizer_is_deferred_not_raised():
    """A KeyboardInterrupt raised inside __del__ is swallowed by Python and cuts the object's clean-up short
    (an rclpy logger finalised that way crashed a node with −11): during start-up such a signal only asks
    for the stop, which run_node honours before spinning."""
    import sys

    policy = InterruptPolicy()
    policy.enter(START)
    seen = {}

    class Finalised:
        def __del__(self):
            frame = sys._getframe()
            try:
                policy._handle(signal.SIGINT, frame)
                seen["raised"] = False
            except KeyboardInterrupt:
                seen["raised"] = True

    obj = Finalised()
    del obj
    assert seen == {"raised": False} and policy.stop_requested and policy.received == 1
    with pytest.raises(KeyboardInterrupt):  # anywhere else during start-up it still raises
        policy._handle(signal.SIGINT, sys._getframe())
