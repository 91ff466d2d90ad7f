"""Ctrl-C ends a node with exit code 0 in every phase (gsrmr_common.interrupts), tested on real processes.

A stand-in package laid out like ours (its ``__init__`` calls ``guard_console_start_up``; its node module has a
slow import, a ``@console_main`` ``main`` with a start-up, a spin loop and a slow clean-up) runs through a
console-script file named ``gsrmr-…`` — setuptools' template (``from pkg.node import main``) or colcon's
(``load_entry_point``) — in a child process; the test sends SIGINT at the moment it wants, as a terminal and
``ros2 launch`` do. One test does the same to the real ``gsrmr-robot`` while it loads.
"""

from __future__ import annotations

import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

from conftest import ros_env
import pytest

from gsrmr_common.interrupts import CLEANUP, RUNNING, START, InterruptPolicy, is_console_script

PACKAGE_INIT = "from gsrmr_common.interrupts import guard_console_start_up\n\nguard_console_start_up()\n"
STAND_IN = '''
import os, time
from gsrmr_common.interrupts import CLEANUP, POLICY, RUNNING, console_main
try:
    print("importing", flush=True)
    time.sleep(float(os.environ.get("IMPORT_S", "0")))
except BaseException:
    if os.environ.get("CONVERT"):  # what a C extension's callback may do with an interrupt
        raise RuntimeError("interrupted inside an extension") from None
    raise
if os.environ.get("FAIL"):
    raise RuntimeError("a real start-up error")

def run():
    print("starting", flush=True)
    time.sleep(float(os.environ.get("START_S", "0")))  # building the node: a KeyboardInterrupt may land here
    POLICY.enter(RUNNING)
    print("running", flush=True)
    while not POLICY.stop_requested:  # as run_node's spin loop: nothing is raised while running
        time.sleep(0.02)
    POLICY.enter(CLEANUP)
    print("cleanup", flush=True)
    time.sleep(1.0)
    print("done", flush=True)
    return 0

main = console_main(run)
plain_main = run  # the same without the decorator
'''
# The console-script files setuptools (pip) and colcon (setup.py develop) write, for stand_in.node:<entry>.
SETUPTOOLS_SCRIPT = '''import re
import sys
from stand_in.node import {entry} as main
if __name__ == "__main__":
    sys.argv[0] = re.sub(r"(-script\\.pyw|\\.exe)?$", "", sys.argv[0])
    sys.exit(main())
'''
COLCON_SCRIPT = '''import importlib
import re
import sys

def importlib_load_entry_point(module, attr):
    return getattr(importlib.import_module(module), attr)

if __name__ == "__main__":
    sys.argv[0] = re.sub(r"(-script\\.pyw?|\\.exe)?$", "", sys.argv[0])
    sys.exit(importlib_load_entry_point("stand_in.node", "{entry}")())
'''
TEMPLATES = {"setuptools": SETUPTOOLS_SCRIPT, "colcon": COLCON_SCRIPT}
# A terminal's Ctrl-C reaches a program whose SIGINT has its default disposition. A test run started in the background
# by a non-interactive shell (`make test &`, a CI script's `cmd &`) ignores SIGINT, and an ignored signal stays ignored
# across exec, so every child here starts through this reset (then execs its command, as a terminal would start it).
FROM_A_TERMINAL = [sys.executable, "-c", "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
                   "os.execvp(sys.argv[1], sys.argv[1:])"]
_children: list[subprocess.Popen] = []


@pytest.fixture(autouse=True)
def _no_child_left():
    """A child a failed test left running (a stand-in in its spin loop) is killed when the test ends."""
    yield
    while _children:
        proc = _children.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def popen_from_a_terminal(command: list[str], **kwargs) -> subprocess.Popen:
    """``subprocess.Popen(command, **kwargs)`` with SIGINT at its default disposition (:data:`FROM_A_TERMINAL`);
    the child is killed at the end of the test if it still runs."""
    proc = subprocess.Popen([*FROM_A_TERMINAL, *command], **kwargs)
    _children.append(proc)
    return proc


def start(tmp_path: Path, import_s: float = 0.0, *, template: str = "setuptools", entry: str = "main",
          script: str = "gsrmr-stand-in", **flags: str) -> subprocess.Popen:
    """Run the stand-in through a console-script file named ``script`` (setuptools' or colcon's template)."""
    package = tmp_path / "stand_in"
    package.mkdir(exist_ok=True)
    (package / "__init__.py").write_text(PACKAGE_INIT)
    (package / "node.py").write_text(STAND_IN)
    (tmp_path / script).write_text(TEMPLATES[template].format(entry=entry))
    env = dict(os.environ, IMPORT_S=str(import_s), **flags, PYTHONPATH=os.pathsep.join([str(tmp_path), *sys.path]))
    return popen_from_a_terminal([sys.executable, str(tmp_path / script)], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True, env=env)


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


@pytest.mark.parametrize("template", sorted(TEMPLATES))
def test_sigint_while_the_node_module_loads_exits_zero(tmp_path, template):
    proc = start(tmp_path, import_s=30.0, template=template)
    wait_line(proc, "importing")
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0 and "starting" not in out and "Traceback" not in err, err


def test_interrupt_turned_into_another_exception_while_loading_still_exits_zero(tmp_path):
    proc = start(tmp_path, import_s=30.0, CONVERT="1")
    wait_line(proc, "importing")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0 and "stopped by a signal while loading (RuntimeError" in err, err


def test_a_real_error_without_a_signal_still_fails(tmp_path):
    proc = start(tmp_path, FAIL="1")
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 1 and "a real start-up error" in err and "Traceback" in err, err


def test_sigint_while_main_builds_the_node_exits_zero(tmp_path):
    proc = start(tmp_path, START_S="30")
    wait_line(proc, "starting")
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0 and "running" not in out and "Traceback" not in err, err


@pytest.mark.parametrize("template", sorted(TEMPLATES))
def test_second_sigint_does_not_cut_the_cleanup_short(tmp_path, template):
    proc = start(tmp_path, template=template)
    wait_line(proc, "running")
    proc.send_signal(signal.SIGINT)  # the terminal's
    wait_line(proc, "cleanup")
    proc.send_signal(signal.SIGINT)  # launch's, while the node cleans up
    out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0 and "done" in out, out


def test_the_guard_is_only_armed_in_a_gsrmr_console_script(tmp_path):
    """A program of another name (here ``stand-in``) keeps Python's own handling: the interrupt ends it by signal."""
    proc = start(tmp_path, import_s=30.0, script="stand-in")
    wait_line(proc, "importing")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == -signal.SIGINT and "KeyboardInterrupt" in err, err
    code = ("import signal, sys; import stand_in.node; print(signal.getsignal(signal.SIGINT) is "
            "signal.default_int_handler, sys.excepthook is sys.__excepthook__)")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), *sys.path]))
    shown = subprocess.run([*FROM_A_TERMINAL, sys.executable, "-c", code], capture_output=True, text=True, env=env,
                           timeout=60)
    assert shown.stdout.split()[-2:] == ["True", "True"], shown.stderr  # importing our packages changed nothing


def test_an_interrupt_after_loading_is_the_entry_functions_to_handle(tmp_path):
    """The loading guard ends with the import: a ``main`` without ``console_main`` that lets the interrupt
    escape while it builds its node ends by signal, as any Python program would."""
    proc = start(tmp_path, START_S="30", entry="plain_main")
    wait_line(proc, "starting")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == -signal.SIGINT and "KeyboardInterrupt" in err, err


def test_a_signal_deferred_while_loading_stops_main_before_it_starts():
    """A start-up signal that landed in a finalizer only asks for the stop: the decorated main returns 0 at once."""
    code = ("from gsrmr_common.interrupts import POLICY, console_main; POLICY.stop_requested = True; called = []; "
            "main = console_main(lambda: called.append(1) or 5); code = main(); print(code, len(called)); "
            "print(main.__wrapped__(), len(called))")
    shown = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert shown.stdout.split() == ["0", "0", "5", "1"], shown.stderr


def test_console_script_names():
    assert is_console_script("/opt/ros/install/lib/gsrmr/gsrmr-server")
    assert is_console_script(".venv/bin/gsrmr-robot")
    assert not is_console_script("/usr/bin/pytest") and not is_console_script("-c")


@pytest.mark.ros
def test_ctrl_c_while_gsrmr_robot_loads_exits_zero(tmp_path):
    """The real console script: SIGINT once its package's guard is in place and its node module is loading
    (``PYTHONPROFILEIMPORTTIME`` reports each import as it ends) exits 0 without a traceback."""
    from gsrmr_sim.sim_stack import executable_path

    env = dict(ros_env(), PYTHONPROFILEIMPORTTIME="1")
    proc = popen_from_a_terminal([str(executable_path("gsrmr-robot"))], env=env, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    watchdog = threading.Timer(120.0, proc.kill)  # the lines below never come: fail instead of hanging
    watchdog.start()
    try:
        seen = []
        for wanted in ("gsrmr_common.interrupts", "numpy"):  # the guard's module; then the node's imports
            for line in proc.stderr:
                seen.append(line)
                if line.split("|")[-1].strip() == wanted:
                    break
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0 and "Traceback" not in err, "".join(seen[-5:]) + err[-2000:]
    assert "robot uplink:" not in out + err  # stopped before the node was built


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


# ------------------------------------------------------------------------------------ exit deadline

DEADLINE_SCRIPT = """
import re, sys, time
from gsrmr_common.interrupts import arm_exit_deadline
assert arm_exit_deadline(float(sys.argv[2]))
print("armed", flush=True)
if sys.argv[1] == "gil":
    re.match(r"(a+)+$", "a" * 40 + "b")  # a C loop that holds the GIL for minutes: no Python timer can run
else:
    time.sleep(0.1)
    sys.exit(3)
"""


def test_exit_deadline_ends_a_process_stuck_in_c_holding_the_gil_with_code_zero(tmp_path):
    """What a Fast DDS livelock in the participant's teardown looks like to Python (interrupts module)."""
    script = tmp_path / "deadline.py"
    script.write_text(DEADLINE_SCRIPT)
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, str(script), "gil", "1.5"], capture_output=True, text=True, timeout=60)
    took = time.monotonic() - t0
    assert done.returncode == 0, done.stderr
    assert "armed" in done.stdout  # flushed before the deadline
    assert "Timeout" in done.stderr and "in match" in done.stderr  # where it hung, dumped 0.5 s before the end
    assert 1.5 <= took < 30.0  # never before the deadline


def test_exit_deadline_leaves_a_process_that_ends_in_time_alone(tmp_path):
    script = tmp_path / "deadline.py"
    script.write_text(DEADLINE_SCRIPT)
    done = subprocess.run([sys.executable, str(script), "finish", "5"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 3 and "Timeout" not in done.stderr
