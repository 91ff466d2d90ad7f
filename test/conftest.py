"""Shared pytest fixtures: an isolated ROS 2 environment and a harness for node processes.

Every test that starts ROS processes gets its own ``ROS_DOMAIN_ID`` and localhost-only discovery, so
parallel runs on one machine (or a developer's other ROS graph) never see each other.
"""

from __future__ import annotations

from collections.abc import Iterator
import os
from pathlib import Path
import signal
import subprocess
import time

import pytest
from ros_domain import USED_DOMAINS, mark_pytest_session, next_domain_id, stop_ros2_daemons

REPO = Path(__file__).resolve().parents[1]


def pytest_configure(config) -> None:
    """This session hands out the ROS domains (:func:`next_domain_id`, one per test); ``launch_support``
    asks it instead of picking a free domain of its own, as it does under a plain ``launch_test``."""
    mark_pytest_session()


def pytest_sessionfinish(session, exitstatus) -> None:
    """Stop the ros2 CLI daemons that this session's `ros2 service call`/`ros2 topic` started (one per
    domain it used): no process outlives the test run."""
    stop_ros2_daemons(USED_DOMAINS)


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
