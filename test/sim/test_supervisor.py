"""The supervisor's process groups (:mod:`gsrmr_sim.supervisor`): a supervised node gets its own process group but
stays in the supervisor's session, so the niceness its ProcessSpec gives it counts against the other nodes (with the
kernel's autogroups, which share the CPU per session first, a node in a session of its own ignored its niceness)."""

from __future__ import annotations

import os
from pathlib import Path
import signal
import sys
import time

from gsrmr_sim.supervisor import ProcessStack


def _stat_fields(pid: int) -> list[str]:
    stat = Path(f"/proc/{pid}/stat").read_bytes()
    return stat[stat.rindex(b")") + 2:].decode().split()  # state, ppid, pgrp, session, ...


def test_a_supervised_process_has_its_own_group_in_the_supervisors_session_and_keeps_its_niceness(tmp_path):
    stack = ProcessStack(dict(os.environ), tmp_path)
    proc = stack.start("sleeper", ["nice", "-n", "7", sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and int(_stat_fields(proc.pid)[16]) != 7:  # nice execs the sleeper
            time.sleep(0.05)
        fields = _stat_fields(proc.pid)
        assert int(fields[2]) == proc.pid, "own process group: killpg reaches it and only it"
        assert int(fields[3]) == os.getsid(0), "the supervisor's session, not one of its own"
        assert int(fields[16]) == 7, "the niceness it was started with"
        autogroup = Path(f"/proc/{proc.pid}/autogroup")
        if autogroup.exists():  # a kernel with CONFIG_SCHED_AUTOGROUP: the same autogroup as the supervisor
            # The file is empty for a task whose cpu cgroup is not the root one (a container): no autogroup applies
            # to either process then, and both read the same empty text.
            assert autogroup.read_text().strip() == Path("/proc/self/autogroup").read_text().strip()
        assert Path(f"/proc/{proc.pid}/fd/0").resolve() == Path(os.devnull), "stdin is /dev/null"
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)


def test_stop_ends_a_supervised_process_on_sigint(tmp_path):
    """The sleeper handles SIGINT itself, as every gsrmr node does: a shell's background job (CI's runner may be
    one) inherits SIGINT ignored, and a plain Python script would then ignore it too."""
    ready = tmp_path / "ready"
    sleeper = ("import pathlib, signal, sys, time\n"
               "signal.signal(signal.SIGINT, lambda *_: sys.exit(3))\n"
               f"pathlib.Path({str(ready)!r}).touch()\n"
               "time.sleep(60)\n")
    stack = ProcessStack(dict(os.environ), tmp_path, stop_timeout_s=20.0)
    proc = stack.start("sleeper", [sys.executable, "-c", sleeper], wait_for_path=str(ready), wait_s=30.0)
    took = stack.stop()
    assert proc.returncode == 3, "ended by its SIGINT handler, not killed"
    assert took["sleeper"] < 20.0
