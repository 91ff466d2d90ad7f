"""Shared pytest fixtures: an isolated ROS 2 environment and a harness for node processes.

Every test that starts ROS processes gets its own ``ROS_DOMAIN_ID`` and localhost-only discovery, so
parallel runs on one machine (or a developer's other ROS graph) never see each other.
"""

from __future__ import annotations

from collections.abc import Iterator
import faulthandler
import os
from pathlib import Path
import signal
import subprocess
import tempfile
import time

import pytest
from support.ros_domain import USED_DOMAINS, mark_pytest_session, next_domain_id, stop_ros2_daemons

REPO = Path(__file__).resolve().parents[1]


def pytest_configure(config) -> None:
    """This session hands out the ROS domains (:func:`next_domain_id`, one per test); ``launch_support``
    asks it instead of picking a free domain of its own, as it does under a plain ``launch_test``."""
    mark_pytest_session()


def pytest_sessionfinish(session, exitstatus) -> None:
    """Stop the ros2 CLI daemons that this session's `ros2 service call`/`ros2 topic` started (one per
    domain it used): no process outlives the test run."""
    stop_ros2_daemons(USED_DOMAINS)
    if _HANG_DUMP["file"] is not None:
        _HANG_DUMP["file"].close()
        Path(_HANG_DUMP["file"].name).unlink(missing_ok=True)


# A deadlock inside Fast DDS (eProsima/Fast-DDS#6502, open: the UDP receive thread holds the PDP mutex while it waits
# for the event thread, which waits for that mutex in check_remote_participant_liveliness) can freeze this process's
# own participant while a remote one goes away; the thread that holds the GIL then waits for ever, so neither
# pytest-timeout's SIGALRM nor any Python thread can end the test (a clean-clone run hung so, 2026-11-26).
# faulthandler's watchdog is a C thread that needs no GIL: past the hard deadline it writes every thread's Python stack
# to the dump file and exits 1, so the run fails with the stacks instead of hanging. tools/run_tests.sh prints the dump.
# pytest-timeout's 300 s per test (pyproject.toml) plus room for its own report
HARD_DEADLINE_S = float(os.environ.get("GSRMR_HARD_DEADLINE_S", "420"))
_HANG_DUMP: dict = {"file": None}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Arm the hard deadline for one test's setup, call and teardown (module fixtures end in the last one's)."""
    if _HANG_DUMP["file"] is None:
        path = os.environ.get("GSRMR_HANG_DUMP") or os.path.join(tempfile.gettempdir(),
                                                                 f"gsrmr-pytest-hang-{os.getpid()}.txt")
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        _HANG_DUMP["file"] = open(path, "w")  # noqa: SIM115 (kept open: faulthandler writes to its descriptor)
    dump = _HANG_DUMP["file"]
    dump.seek(0)
    dump.truncate()
    dump.write(f"{item.nodeid}: no end within {HARD_DEADLINE_S:.0f} s (started {time.strftime('%H:%M:%S')})\n")
    dump.flush()
    faulthandler.dump_traceback_later(HARD_DEADLINE_S, exit=True, file=dump)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


def ros_env(domain_id: int | None = None) -> dict[str, str]:
    """Environment for a node process: isolated domain, localhost discovery, unbuffered output."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(next_domain_id() if domain_id is None else domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_LOCALHOST_ONLY", None)
    env["PYTHONUNBUFFERED"] = "1"
    env["RCUTILS_LOGGING_BUFFERED_STREAM"] = "0"
    return env


class ProcessHarness:
    """Starts console scripts as real processes in one ROS domain and stops them at teardown."""

    def __init__(self, tmp_path: Path) -> None:
        self.env = ros_env()
        self.tmp_path = tmp_path
        self.procs: list[tuple[subprocess.Popen, Path, Path]] = []

    def start(self, script: str, *args: str) -> subprocess.Popen:
        """Start console script ``<script> args…`` where the installed package exposes it
        (:func:`gsrmr_sim.sim_stack.executable_path`); stdout/stderr go to files under tmp_path."""
        from gsrmr_sim.sim_stack import executable_path

        exe = executable_path(script)
        n = len(self.procs)
        out, err = self.tmp_path / f"{n}-{script}.out", self.tmp_path / f"{n}-{script}.err"
        proc = subprocess.Popen([str(exe), *args], env=self.env, stdout=out.open("w"), stderr=err.open("w"),
                                cwd=self.tmp_path, start_new_session=True)
        self.procs.append((proc, out, err))
        return proc

    def output(self, proc: subprocess.Popen) -> tuple[str, str]:
        """(stdout, stderr) written so far by a started process."""
        for p, out, err in self.procs:
            if p is proc:
                return out.read_text(), err.read_text()
        raise KeyError(proc)

    def wait_for(self, proc: subprocess.Popen, text: str, timeout_s: float, stream: str = "any") -> str:
        """Wait until ``text`` appears in the process output; fail with the output if it never does."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            out, err = self.output(proc)
            hay = {"stdout": out, "stderr": err}.get(stream, out + err)
            if text in hay:
                return hay
            if proc.poll() is not None:
                break
            time.sleep(0.05)
        out, err = self.output(proc)
        pytest.fail(f"{text!r} not seen within {timeout_s}s (rc={proc.poll()})\n"
                    f"stdout:\n{out}\nstderr:\n{err}")

    def interrupt(self, proc: subprocess.Popen, timeout_s: float = 10.0) -> float:
        """SIGINT the process; return seconds until it exited (fail if it did not exit in time)."""
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            pytest.fail(f"process did not exit within {timeout_s}s of SIGINT: {proc.args}")
        return time.monotonic() - t0

    def close(self) -> None:
        for proc, _, _ in self.procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=10)


@pytest.fixture
def ros_processes(tmp_path: Path) -> Iterator[ProcessHarness]:
    """A :class:`ProcessHarness` whose processes are killed at teardown."""
    harness = ProcessHarness(tmp_path)
    try:
        yield harness
    finally:
        harness.close()


@pytest.fixture
def ros_context(monkeypatch):
    """An rclpy context in a ROS domain of its own, discovery on this host only (rclpy imported here: pure tests run
    without ROS)."""
    import rclpy

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=next_domain_id())
    try:
        yield ctx
    finally:
        rclpy.shutdown(context=ctx)
