"""Supervising a stack of processes: one implementation for the demo, the test stacks and the benches.

:class:`ProcessStack` starts each process in its own process group, in the supervisor's session
(:data:`OWN_PROCESS_GROUP`), logs its output to ``<log_dir>/<name>.log``, reports one that died and stops them all
as a terminal's Ctrl-C would (:meth:`ProcessStack.stop`). A process is a
:class:`~gsrmr_sim.sim_stack.ProcessSpec` or a plain argv.
"""

from __future__ import annotations

from collections.abc import Sequence
import os
from pathlib import Path
import shutil
import signal
import subprocess
import time
from types import TracebackType

from gsrmr_common.interrupts import STACK_DUMP_SIGNAL
from gsrmr_sim.sim_stack import ProcessSpec, command_line

#: ``subprocess.Popen`` keywords of every supervised process: its own process group (``killpg`` reaches its threads'
#: and children's processes; the terminal's Ctrl-C reaches only the supervisor, which stops the stack in order), but
#: **not its own session**. With ``kernel.sched_autogroup_enabled`` = 1 (Ubuntu's and most distributions' default)
#: the scheduler first shares the CPU equally between *sessions* (autogroups) and applies ``nice`` only inside one:
#: a node started with ``start_new_session`` at nice 19 took as much CPU as the server at nice 0 (the simulated
#: world's scorer, 40–58 % of a core in the last seconds of a round, which made 14–80 of 288 slots late,
#: docs/results.md). In the supervisor's session, a node's niceness orders it against the others as its
#: ProcessSpec says. stdin is /dev/null: a background process group that read the terminal would be stopped.
OWN_PROCESS_GROUP: dict = {"process_group": 0, "stdin": subprocess.DEVNULL}


class ProcessDiedError(RuntimeError):
    """A supervised process exited while it was meant to run."""


class ProcessStack:
    """Processes started, watched and stopped together (see the module docstring)."""

    def __init__(self, env: dict[str, str], log_dir: str | Path, *, params_dir: str | Path | None = None,
                 stop_timeout_s: float = 15.0) -> None:
        self.env = env
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.params_dir = Path(params_dir) if params_dir is not None else self.log_dir / "params"
        self.stop_timeout_s = stop_timeout_s
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, what: ProcessSpec | Sequence[str], *, wait_for_path: str | None = None,
              wait_s: float = 10.0, prefix: Sequence[str] = (), env: dict[str, str] | None = None) -> subprocess.Popen:
        """Start ``what`` as ``name`` (output appended to its log); with ``wait_for_path``, return once that
        path exists (e.g. the mock LIMO's pty) or raise :class:`ProcessDiedError` / TimeoutError. ``prefix`` is
        put before the command (e.g. ``ip netns exec <ns>``, which execs it: signals still reach the node);
        ``env`` replaces the stack's environment for this process."""
        argv = command_line(what, None, self.params_dir) if isinstance(what, ProcessSpec) else list(what)
        argv = [*prefix, *argv]
        log = (self.log_dir / f"{name}.log").open("a")
        proc = subprocess.Popen(argv, env=self.env if env is None else env, stdout=log, stderr=subprocess.STDOUT,
                                **OWN_PROCESS_GROUP)
        log.close()  # the child holds its own descriptor
        self.procs[name] = proc
        if wait_for_path is not None:
            deadline = time.monotonic() + wait_s
            while not os.path.exists(wait_for_path):
                self.check(name)
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{name}: {wait_for_path} did not appear in {wait_s} s\n"
                                       f"{self.log(name)[-2000:]}")
                time.sleep(0.05)
        return proc

    def log(self, name: str) -> str:
        """Everything ``name`` printed so far."""
        path = self.log_dir / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def check(self, *names: str) -> None:
        """Raise :class:`ProcessDiedError` if any of ``names`` (default: all) has exited."""
        for name in names or tuple(self.procs):
            proc = self.procs[name]
            if proc.poll() is not None:
                raise ProcessDiedError(f"{name} exited with {proc.returncode}; see {self.log_dir / (name + '.log')}")

    def kill9(self, name: str) -> None:
        """SIGKILL a process's group and reap it."""
        proc = self.procs[name]
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)

    def stop(self) -> dict[str, float]:
        """SIGINT every running process (newest first), SIGKILL the group of those still running after
        ``stop_timeout_s``; returns the seconds each took to exit."""
        for proc in reversed(list(self.procs.values())):
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        took = {}
        for name, proc in self.procs.items():
            t0 = time.monotonic()
            try:
                proc.wait(timeout=self.stop_timeout_s)
            except subprocess.TimeoutExpired:
                self._dump_stacks(name, proc)
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            took[name] = time.monotonic() - t0
        return took

    def _dump_stacks(self, name: str, proc: subprocess.Popen) -> None:
        """Before a hung process is killed: its threads' Python stacks into its log (a gsrmr console
        script prints them on SIGUSR1, see :mod:`gsrmr_common.interrupts`; the kernel's view of each
        thread's state and wait channel is added from /proc)."""
        with (self.log_dir / f"{name}.log").open("a") as log:
            log.write(f"\n[supervisor] {name} (pid {proc.pid}) still running {self.stop_timeout_s} s after "
                      f"SIGINT; its threads:\n")
            for task in sorted(Path(f"/proc/{proc.pid}/task").glob("*")):
                try:
                    comm = (task / "comm").read_text().strip()
                    state = (task / "stat").read_text().rsplit(")", 1)[1].split()[0]
                    wchan = (task / "wchan").read_text().strip()
                except OSError:
                    continue
                log.write(f"[supervisor]   tid {task.name} {comm!r} state {state} wchan {wchan}\n")
        try:
            proc.send_signal(STACK_DUMP_SIGNAL)
            time.sleep(1.0)
        except ProcessLookupError:
            return
        gdb = shutil.which("gdb")
        if gdb is not None:  # the native stacks too (where the Python stack ends in a C extension)
            with (self.log_dir / f"{name}.log").open("a") as log:
                log.write("[supervisor] native stacks (gdb):\n")
                log.flush()
                subprocess.run([gdb, "-p", str(proc.pid), "-batch", "-nx", "-ex", "thread apply all bt 30"],
                               stdout=log, stderr=subprocess.STDOUT, timeout=60, check=False)

    def __enter__(self) -> ProcessStack:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
