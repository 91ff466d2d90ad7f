"""How a gsrmr process ends on Ctrl-C: exit code 0 whenever the stop was asked for, in any phase.

:class:`InterruptPolicy` (the phase-dependent SIGINT/SIGTERM handler), :func:`guard_console_start_up` (loading),
:func:`console_main` (a node's ``main``) and :func:`arm_exit_deadline` (the DDS teardown). Why each phase needs what
it gets: docs/architecture.md, "Ending on Ctrl-C". Pure Python, no rclpy, no gsrmr import: every package imports it
first.
"""

from __future__ import annotations

from collections.abc import Callable
import contextlib
import ctypes
import faulthandler
import functools
import os
import signal
import sys
import threading
from types import FrameType, TracebackType
from typing import ParamSpec

P = ParamSpec("P")

START, RUNNING, CLEANUP = "start", "running", "cleanup"
#: Every console script of setup.py is named ``gsrmr-…``: a process whose program has such a name is one.
CONSOLE_SCRIPT_PREFIX = "gsrmr-"
#: The attribute :func:`console_main` sets on the function it returns (what the import-rule tests look for).
CONSOLE_MAIN_MARK = "__gsrmr_console_main__"
_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: The signal on which a console script prints every thread's Python stack to stderr (and goes on).
STACK_DUMP_SIGNAL = signal.SIGUSR1
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


def ignore_signals() -> None:
    """Ignore SIGINT and SIGTERM from now on: the process is ending.

    The interpreter's own shutdown (atexit, joining threads, freeing numba/torch) can take a moment, and
    Python restores SIG_DFL for handled signals on the way: a signal arriving then (launch's SIGINT after
    the terminal's) would kill the process with −2. Ignored handlers are kept.
    """
    if threading.current_thread() is threading.main_thread():
        for sig in _SIGNALS:
            signal.signal(sig, signal.SIG_IGN)


class _SigevThread(ctypes.Structure):
    _fields_ = [("function", ctypes.c_void_p), ("attribute", ctypes.c_void_p)]


class _SigevUnion(ctypes.Union):
    _fields_ = [("pad", ctypes.c_int * 12), ("tid", ctypes.c_int), ("thread", _SigevThread)]


class _Sigevent(ctypes.Structure):
    """glibc's ``struct sigevent`` (64 bytes on 64-bit Linux)."""

    _fields_ = [("value", ctypes.c_void_p), ("signo", ctypes.c_int), ("notify", ctypes.c_int),
                ("union", _SigevUnion)]


class _Timespec(ctypes.Structure):
    _fields_ = [("sec", ctypes.c_long), ("nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("interval", _Timespec), ("value", _Timespec)]


_SIGEV_THREAD = 2
_CLOCK_MONOTONIC = 1
_exit_timer = ctypes.c_void_p()  # the armed timer (kept: timer_delete would disarm it)


def arm_exit_deadline(seconds: float) -> bool:
    """End this process with exit code 0 at the latest ``seconds`` from now, whatever its threads do then.

    For the teardown of a process whose own clean-up is done (files closed, devices released), when a C
    library may hang holding the GIL — no Python-level timer could run then. A POSIX timer
    (``timer_create`` with ``SIGEV_THREAD``) calls libc's ``_exit`` with the timer's value 0 from a thread
    libc starts: no Python, no GIL, no signal to the program. Python's buffers are flushed first; a traceback
    of every thread is written to stderr 0.5 s before the deadline (:mod:`faulthandler`), so a teardown that
    needed the deadline shows where it hung. Arming again moves the deadline. Returns False where the C
    library has no such timer (not glibc/Linux): nothing is armed then.
    """
    if not seconds > 0.5:
        raise ValueError(f"exit deadline must be > 0.5 s, got {seconds}")
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        timer_create, timer_settime, exit_now = libc.timer_create, libc.timer_settime, libc._exit
    except (OSError, AttributeError):
        return False
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(AttributeError, OSError, ValueError):
            stream.flush()
    if not _exit_timer.value:
        event = _Sigevent()
        event.value = None  # the sigval passed to _exit: status 0
        event.notify = _SIGEV_THREAD
        event.union.thread.function = ctypes.cast(exit_now, ctypes.c_void_p).value
        if timer_create(_CLOCK_MONOTONIC, ctypes.byref(event), ctypes.byref(_exit_timer)) != 0:
            _exit_timer.value = None
            return False
    whole = int(seconds)
    when = _Itimerspec(_Timespec(0, 0), _Timespec(whole, int((seconds - whole) * 1e9)))
    if timer_settime(_exit_timer, 0, ctypes.byref(when), None) != 0:
        return False
    with contextlib.suppress(RuntimeError, ValueError):  # no usable stderr: no traceback
        faulthandler.dump_traceback_later(seconds - 0.5, repeat=False)
    return True


def _program() -> str:
    return os.path.basename(sys.argv[0]) if getattr(sys, "argv", None) else "python"


def console_main(main: Callable[P, int | None]) -> Callable[P, int]:
    """Decorate the ``main`` a console script calls (a node module's): exit code 0 when interrupted.

    The returned function installs :data:`POLICY` (phase START), returns 0 at once for a signal deferred
    while the module loaded, calls ``main`` and returns its code; a ``KeyboardInterrupt`` returns 0, and so
    does any other exception raised after a signal (library code that turned the interrupt into another
    error: a C extension's callback, a half-done ``rclpy.init``), with a note on stderr. Afterwards the
    process ignores SIGINT/SIGTERM (:func:`ignore_signals`): it is a process's entry, not a function to
    call in a longer-lived process (``main.__wrapped__`` is the plain function).
    """

    @functools.wraps(main)
    def entry(*args: P.args, **kwargs: P.kwargs) -> int:
        POLICY.install()
        POLICY.enter(START)
        try:
            if POLICY.stop_requested:  # a signal deferred while the module loaded (InterruptPolicy._handle)
                return 0
            return int(main(*args, **kwargs) or 0)
        except KeyboardInterrupt:
            return 0
        except Exception as err:
            if POLICY.received == 0:
                raise
            print(f"{_program()}: stopped by a signal during {POLICY.phase} ({type(err).__name__}: {err})",
                  file=sys.stderr, flush=True)
            return 0
        finally:
            ignore_signals()

    setattr(entry, CONSOLE_MAIN_MARK, True)
    return entry


def is_console_script(program: str | None = None) -> bool:
    """Whether this process runs one of gsrmr's console scripts (``program``: default ``sys.argv[0]``).

    ``ros2 run``, ``ros2 launch`` (``lib/gsrmr/gsrmr-…``, also behind ``nice``) and a venv's ``bin/gsrmr-…``
    all start the script file itself, so the program's name is the console script's name."""
    name = os.path.basename(program if program is not None else _program())
    return name.startswith(CONSOLE_SCRIPT_PREFIX)


_guarded = False


def guard_console_start_up() -> None:
    """In a gsrmr console script, before its entry module loads: Ctrl-C while it loads ends it with code 0.

    Called by the ``__init__`` of every package that holds a console script's module (Python imports the
    package before the module). In a console script (:func:`is_console_script`), in the main thread, once:
    install :data:`POLICY` (phase START: a signal raises ``KeyboardInterrupt``, or is deferred inside a
    finalizer) and an exception hook that turns an interrupt ending the program *while it loads its entry
    module* into exit code 0 (silently for the ``KeyboardInterrupt``, with a note for an exception raised
    after a signal). An exception raised once the script's entry function runs keeps Python's handling;
    a node's ``main`` handles its own (:func:`console_main`). Anywhere else (pytest, a Python shell,
    ``python -m``) it does nothing.
    """
    global _guarded
    if _guarded or threading.current_thread() is not threading.main_thread() or not is_console_script():
        return
    _guarded = True
    faulthandler.register(STACK_DUMP_SIGNAL, all_threads=True, chain=False)
    POLICY.install()
    POLICY.enter(START)
    previous = sys.excepthook

    def start_up_excepthook(exc_type: type[BaseException], exc: BaseException, tb: TracebackType | None) -> None:
        interrupted = issubclass(exc_type, KeyboardInterrupt) or POLICY.received > 0
        if interrupted and POLICY.phase == START and _while_loading(tb):
            ignore_signals()
            if not issubclass(exc_type, KeyboardInterrupt):
                print(f"{_program()}: stopped by a signal while loading ({exc_type.__name__}: {exc})",
                      file=sys.stderr, flush=True)
            raise SystemExit(0)  # from an exception hook: CPython exits with this code (after its clean-up)
        previous(exc_type, exc, tb)

    sys.excepthook = start_up_excepthook


def _while_loading(tb: TracebackType | None) -> bool:
    """Whether the traceback of an exception that ended the program shows it still loading its entry module.

    The first entry is ``__main__``'s code (the console script); the second is what it called: a module
    body (``from package.module import main``: the import machinery's frames are left out of tracebacks),
    or a helper of the script itself (``load_entry_point``, as colcon's scripts load the entry) — or, once
    loaded, the entry function, which is no longer loading."""
    called = tb.tb_next if tb is not None else None
    if called is None:  # raised in the script's own statements (its first imports)
        return True
    frame = called.tb_frame
    module = str(frame.f_globals.get("__name__", ""))
    return frame.f_code.co_name == "<module>" or module == "__main__" or module.startswith("importlib")
