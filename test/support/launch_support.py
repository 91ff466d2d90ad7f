"""Helpers of the tests that run the installed launch files and the ``ros2`` command line.

They test what a ROS user types: the launch files are found through the ament index (``colcon build``
and a sourced ``install/setup.bash``, which ``make test`` does), and the CLI is the real ``ros2``
(``ros2cli`` from ``../shared/ros-tooling`` or a ROS install). Where that tooling is missing (a fresh
clone without ``../shared``), :func:`require_ros_tooling` skips the module with the reason.

No conftest needed: a launch test run by plain ``launch_test test/launch/<file>`` (no pytest) imports this
module too, after putting ``test/`` on ``sys.path`` (:func:`isolate_this_process` then picks a free ROS
domain itself and says which).
"""

from __future__ import annotations

import atexit
import contextlib
from dataclasses import dataclass
import os
from pathlib import Path
import re
import shutil
import signal
import subprocess
import sys
import time

import pytest

from gsrmr_sim.sim_stack import sim_stack
from support.ros_domain import free_domain_id, in_pytest_session, next_domain_id, stop_ros2_daemons

DOMAIN_NOTE = "[launch_support] ROS_DOMAIN_ID="  # how a plain launch_test run says which domain it picked


def ros_tooling_missing() -> str | None:
    """Why the launch tests cannot run here (None when they can): launch, launch_testing, ros2cli and an
    ament-indexed gsrmr are needed."""
    import importlib.util

    for module in ("launch", "launch_ros", "launch_testing", "ros2cli"):
        if importlib.util.find_spec(module) is None:
            return f"{module} is not installed: no ROS 2 install and no ../shared/ros-tooling"
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

    try:
        get_package_share_directory("gsrmr")
    except (PackageNotFoundError, LookupError, OSError):  # OSError: AMENT_PREFIX_PATH not set at all
        return "gsrmr is not ament-indexed: run `make test` (colcon build, source install/setup.bash)"
    if shutil.which("ros2") is None:
        return "the ros2 command is not on PATH"
    return None


def require_ros_tooling() -> pytest.MarkDecorator:
    """Skip the calling module where the launch tooling is missing; return the mark for its tests.

    Without ``launch_testing`` its pytest plugin is not loaded and a module-level skip is safe. With it,
    the plugin imports every test module while *collecting the directory*, and a module-level skip
    would skip the whole ``test/`` folder: there the caller marks its tests with the returned
    ``skipif`` instead (a mark on ``generate_test_description`` applies to the launch test module).
    """
    import importlib.util

    reason = ros_tooling_missing()
    if reason is not None and importlib.util.find_spec("launch_testing") is None:
        pytest.skip(reason, allow_module_level=True)
    return pytest.mark.skipif(reason is not None, reason=reason or "")


def launch_file(name: str) -> str:
    """The installed launch file ``share/gsrmr/launch/<name>`` (as ``ros2 launch gsrmr <name>`` finds it)."""
    from ament_index_python.packages import get_package_share_directory

    return os.path.join(get_package_share_directory("gsrmr"), "launch", name)


def sim_process_names() -> list[str]:
    """The node names of the processes ``sim.launch.py`` starts: it builds them from
    :func:`gsrmr_sim.sim_stack.sim_stack`, so the tests count them from there too."""
    return [spec.name for spec in sim_stack(model_path="model.ply")]


def isolate_this_process() -> int:
    """Give this test process (and what it launches) a fresh ROS domain with localhost discovery; the domain.

    Under pytest (``colcon test``, ``make test``) the session's conftest hands the domain out. Under a
    plain ``launch_test test/launch/<file>`` there is no conftest: the domain is a free one of this host
    (:func:`ros_domain.free_domain_id`), printed on stdout, and any ros2 daemon the test's CLI calls
    started in it is stopped when the process exits. There, missing tooling is an error with its reason
    (``launch_test`` ignores the pytest skip mark).
    """
    if in_pytest_session():
        domain = next_domain_id()
    else:
        missing = ros_tooling_missing()
        if missing is not None:
            raise RuntimeError(missing)
        domain = free_domain_id()
        atexit.register(stop_ros2_daemons, {domain})
        print(f"{DOMAIN_NOTE}{domain} (no DDS port of it bound on this host), ROS_AUTOMATIC_DISCOVERY_RANGE="
              f"LOCALHOST: this launch test's processes and ros2 calls use that domain", file=sys.stdout, flush=True)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    os.environ["PYTHONUNBUFFERED"] = "1"
    return domain


def ros2(*args: str, timeout_s: float = 30.0, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """Run ``ros2 <args>`` as a user would, in the current environment; never leaves a daemon behind
    (callers pass ``--no-daemon`` where the verb has it)."""
    try:
        return subprocess.run(["ros2", *args], capture_output=True, text=True, timeout=timeout_s,
                              env=env or dict(os.environ))
    except subprocess.TimeoutExpired as late:  # e.g. `topic echo --once` on a silent topic: report, don't raise
        out = late.stdout.decode(errors="replace") if isinstance(late.stdout, bytes) else (late.stdout or "")
        return subprocess.CompletedProcess(late.cmd, -9, out, f"timed out after {timeout_s} s")


def ros2_until(*args: str, ok: str | tuple[str, ...], attempts: int = 10, pause_s: float = 1.0,
               timeout_s: float = 30.0) -> subprocess.CompletedProcess:
    """Run a ``ros2`` command until its output (stdout or stderr) contains ``ok`` (or one of them:
    discovery of a just-started node takes a moment and ``--no-daemon`` CLIs have no discovery cache);
    return the last result."""
    wanted = (ok,) if isinstance(ok, str) else ok
    result = ros2(*args, timeout_s=timeout_s)
    for _ in range(attempts - 1):
        if any(w in result.stdout + result.stderr for w in wanted):
            break
        time.sleep(pause_s)
        result = ros2(*args, timeout_s=timeout_s)
    return result


@dataclass
class LaunchRun:
    """A ``ros2 launch`` command running in its own session, as a terminal would run it."""

    proc: subprocess.Popen
    log_dir: Path
    stdout_path: Path

    def output(self) -> str:
        """Everything the command printed so far (stdout and stderr)."""
        return self.stdout_path.read_text(errors="replace")

    def wait_for(self, text: str, timeout_s: float) -> bool:
        """True once ``text`` appears in the output (False on timeout or exit)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if text in self.output():
                return True
            if self.proc.poll() is not None:
                return text in self.output()
            time.sleep(0.1)
        return False

    def started_pids(self) -> dict[str, int]:
        """Per process launch has started so far (its launch name, e.g. ``gsrmr-robot-2``): its pid."""
        return {name: int(pid) for name, pid in _STARTED.findall(self.output())}

    def wait_until_loading(self, count: int, library: str, timeout_s: float) -> bool:
        """True once ``count`` processes have started and every one has mapped ``library`` (a substring of a
        shared object's path in ``/proc/<pid>/maps``): each has left the interpreter's own start-up and is
        loading its program's modules. False on timeout, on exit, or when a process ended first."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self.proc.poll() is None:
            pids = self.started_pids()
            if len(pids) >= count and all(_maps_has(pid, library) for pid in pids.values()):
                return True
            time.sleep(0.005)
        return False

    def ctrl_c(self, timeout_s: float = 40.0) -> int:
        """SIGINT to the whole process group (a terminal's Ctrl-C); wait for the command to end."""
        os.killpg(self.proc.pid, signal.SIGINT)
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
            pytest.fail(f"ros2 launch did not end within {timeout_s} s of Ctrl-C:\n{self.output()[-4000:]}")

    def kill(self) -> None:
        """SIGKILL the whole process group (test clean-up)."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=10)

    def launch_log(self) -> str:
        """The launch log (``$ROS_LOG_DIR/launch.log``) that ``ros2 launch`` wrote."""
        logs = sorted(self.log_dir.rglob("launch.log"))
        assert logs, f"no launch.log under {self.log_dir}"
        return "\n".join(p.read_text(errors="replace") for p in logs)


def _maps_has(pid: int, library: str) -> bool:
    """Whether process ``pid`` has a shared object whose path contains ``library`` mapped (False once gone)."""
    try:
        return library in Path(f"/proc/{pid}/maps").read_text(errors="replace")
    except OSError:
        return False


def start_ros2_launch(tmp_path: Path, *args: str, env: dict[str, str] | None = None) -> LaunchRun:
    """``ros2 launch <args>`` in a new session (its own process group) with its logs under tmp_path;
    ``env`` (default: this process's environment) carries the ROS domain."""
    log_dir = tmp_path / "ros_log"
    log_dir.mkdir(parents=True, exist_ok=True)
    env = dict(env or os.environ, ROS_LOG_DIR=str(log_dir), PYTHONUNBUFFERED="1")
    out = tmp_path / "ros2_launch.out"
    proc = subprocess.Popen(["ros2", "launch", *args], stdout=out.open("w"), stderr=subprocess.STDOUT, env=env,
                            start_new_session=True, cwd=tmp_path)
    return LaunchRun(proc, log_dir, out)


_STARTED = re.compile(r"\[INFO\] \[([^\]]+)\]: process started with pid \[(\d+)\]")
_ENDED = re.compile(r"\[(?:INFO|ERROR)\] \[([^\]]+)\]: process (has finished cleanly|has died) \[pid (\d+)"
                    r"(?:, exit code (-?\d+))?")


def exit_codes_from_launch_log(text: str) -> dict[str, int | None]:
    """Per process started by launch (its launch name, e.g. ``gsrmr-robot-5``): the exit code the launch
    log reports (0 for "finished cleanly"), or None when the log reports no exit at all."""
    codes: dict[str, int | None] = {name: None for name, _pid in _STARTED.findall(text)}
    for name, how, _pid, code in _ENDED.findall(text):
        codes[name] = 0 if how == "has finished cleanly" else int(code)
    return codes
