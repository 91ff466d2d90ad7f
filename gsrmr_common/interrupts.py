"""How a gsrmr process ends on Ctrl-C: exit code 0 whenever the stop was asked for, in any phase.

A shell's Ctrl-C sends SIGINT to the whole process group: ``ros2 launch`` and every node get it at
once, and ``launch`` then sends each node a SIGINT of its own (SIGTERM 5 s later, SIGKILL after 10 s).
A Python process that lets the resulting ``KeyboardInterrupt`` escape ends by signal (exit code −2)
and ``launch`` reports "process has died". That happens in three places, each handled here:

* **start-up** (importing numba/torch, loading a model, compiling kernels — seconds): the interrupt
  must stop the process at once. :class:`InterruptPolicy` raises ``KeyboardInterrupt`` in this phase;
  :func:`node_entry` catches it around the import and the node's ``main`` and returns 0.
* **running**: the spin must end through rclpy, never through an exception raised at an arbitrary
  bytecode: a ``KeyboardInterrupt`` that lands between an executor's ``ExitStack.enter_context(handle)``
  and the registration of its exit leaves the handle "in use", and ``destroy_node`` then spins forever
  in ``destroy_when_not_in_use`` (seen: a base driver at 98 % CPU after Ctrl-C); shutting rclpy down
  from the handler mid-executor crashed a node (−11). The policy only sets
  :attr:`InterruptPolicy.stop_requested`; ``run_node`` spins in 0.1 s steps and stops when it is set
  (or when rclpy's own handler has shut the context down, whichever comes first).
* **clean-up** (destroying the node, closing a recording, releasing the serial port): the second
  SIGINT — the one ``launch`` forwards — must not interrupt it. The policy ignores it; only a third
  signal (a user who insists) raises.

* **interpreter exit**: :func:`node_entry` ignores both signals once ``main`` has returned.

SIGTERM is treated as SIGINT. Pure Python, no rclpy: the robot, the server and the tests use it.
"""

from __future__ import annotations

from collections.abc import Callable
import importlib
import signal
import sys
import threading
from types import FrameType

START, RUNNING, CLEANUP = "start", "running", "cleanup"
_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# Signals received during clean-up before a KeyboardInterrupt is raised anyway (a user who insists).
CLEANUP_PATIENCE = 2


class InterruptPolicy:
    """A process-wide SIGINT/SIGTERM handler whose reaction depends on the phase the process is in."""

    def __init__(self) -> None:
        self.phase = START
        self.received = 0
        self._cleanup_received = 0
        self.stop_requested = False

    def install(self) -> InterruptPolicy:
        """Install the handler for SIGINT and SIGTERM (main thread only; elsewhere a no-op)."""
        if threading.current_thread() is threading.main_thread():
            for sig in _SIGNALS:
                signal.signal(sig, self._handle)
        return self

    def enter(self, phase: str) -> None:
        """Switch to ``START``, ``RUNNING`` or ``CLEANUP`` (does not touch the installed handlers, so
        rclpy's handler, chained in front of this one at ``rclpy.init``, stays in place)."""
        if phase not in (START, RUNNING, CLEANUP):
            raise ValueError(f"unknown phase {phase!r}")
        self.phase = phase
        self._cleanup_received = 0

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.received += 1
        if self.phase == START:
            if _in_finalizer(frame):
                # Raised inside a __del__, the KeyboardInterrupt is swallowed ("Exception ignored") and the
                # object's clean-up is cut short: an rclpy logger finalised that way crashed the LIMO base
                # node with −11 in a clean-clone CI run. Defer: run_node never starts spinning.
                self.stop_requested = True
                return
            raise KeyboardInterrupt
        if self.phase == RUNNING:
            self.stop_requested = True
        if self.phase == CLEANUP:
            self._cleanup_received += 1
            if self._cleanup_received > CLEANUP_PATIENCE:
                raise KeyboardInterrupt


def _in_finalizer(frame: FrameType | None) -> bool:
    """Whether the interrupted code runs inside a ``__del__`` (anywhere up the stack)."""
    while frame is not None:
        if frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


POLICY = InterruptPolicy()


def node_entry(target: str) -> Callable[[], int]:
    """A console-script entry for ``"package.module:function"`` that exits 0 when interrupted.

    The module is imported inside the guard, so a Ctrl-C during the (slow) import ends the process
    with code 0 instead of a traceback and −2.
    """
    module_name, function_name = target.split(":")

    def main() -> int:
        POLICY.install()
        POLICY.enter(START)
        try:
            function = getattr(importlib.import_module(module_name), function_name)
            if POLICY.stop_requested:  # a signal deferred during the import (see InterruptPolicy._handle)
                return 0
            return int(function() or 0)
        except KeyboardInterrupt:
            return 0
        except Exception as err:
            if POLICY.received == 0:
                raise
            # An interrupt landed inside library code that turned it into another exception (a C
            # extension's callback, a half-done rclpy.init): the stop was still asked for.
            print(f"{target}: stopped by a signal during {POLICY.phase} ({type(err).__name__}: {err})",
                  file=sys.stderr, flush=True)
            return 0
        finally:
            # The interpreter's own shutdown (atexit, joining threads, freeing numba/torch) can take a
            # moment, and Python restores SIG_DFL for handled signals on the way: a signal arriving then
            # (launch's SIGINT after the terminal's) would kill the process with −2. Ignored handlers
            # are kept; the process is ending anyway.
            for sig in _SIGNALS:
                signal.signal(sig, signal.SIG_IGN)

    main.__doc__ = f"Console entry of {target} (exit 0 on SIGINT/SIGTERM)."
    return main


# The deployment nodes' console scripts (setup.py): every one ends with code 0 on Ctrl-C. The simulator's
# are in gsrmr_sim.entries.
link_echo = node_entry("gsrmr_common.link_check:echo_main")
link_probe = node_entry("gsrmr_common.link_check:probe_main")
limo_base = node_entry("gsrmr_robot.limo.node:main")
robot = node_entry("gsrmr_robot.robot_node:main")
server = node_entry("gsrmr_server.server_node:main")
scheduler = node_entry("gsrmr_server.scheduler_node:main")
