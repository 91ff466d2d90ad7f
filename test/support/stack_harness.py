"""Test helpers shared by the node-suite and reliability tests: the simulated stack as processes.

:class:`Stack` starts the processes of :func:`gsrmr_sim.sim_stack.sim_stack` (plus any extra
:class:`~gsrmr_sim.sim_stack.ProcessSpec`) in one isolated ROS domain; :func:`ros_client` gives the
test an rclpy node and executor in that domain; :func:`make_small_model` trains the small GS model the
node suite uses, :func:`make_point_model` writes a cheap untrained one (enough for fault tests).
"""

from __future__ import annotations

from collections.abc import Iterator
import contextlib
import os
from pathlib import Path
import subprocess
import time

import numpy as np

WIDTH, HEIGHT = 160, 120


def make_small_model(folder: Path, width: int = WIDTH, height: int = HEIGHT) -> Path:
    """A GS model of the sandbox from 12 round-1 frames (depth-initialised, briefly trained)."""
    from gsrmr_sim.models import ModelRecipe, build_model
    from gsrmr_splat.train import TrainConfig

    recipe = ModelRecipe("sandbox", frames=12, width=width, height=height, holdout_every=0,
                         config=TrainConfig(init_points=6000, sh_degree=0, iterations=60, densify_from=10_000))
    return build_model(recipe, folder=folder, log=lambda _msg: None).path


def make_point_model(folder: Path, n: int = 2000, seed: int = 0) -> Path:
    """An untrained model: ``n`` random coloured Gaussians over the sandbox (x, y in ±5 m, z in 0..2 m)."""
    from gsrmr_splat.model import GaussianModel

    rng = np.random.default_rng(seed)
    model = GaussianModel.from_points(rng.uniform([-5, -5, 0], [5, 5, 2], (n, 3)), rng.uniform(0, 1, (n, 3)),
                                      scales_m=0.08, opacities=0.6)
    return model.save_ply(Path(folder) / "points.ply")


class Stack:
    """The simulated system as processes in one isolated ROS domain (a :class:`~gsrmr_sim.supervisor.ProcessStack`).

    ``overrides`` are merged into the node suite's defaults (per node name); ``remappings`` are added
    to the named node's spec; ``extra`` specs (e.g. a relay) are started after the others. With ``hosts``
    (an open :class:`gsrmr_sim.netns.TwoHosts`) every process runs in its spec's host namespace, DDS over UDPv4
    across the veth, the server's ground truth over the simulation backplane (``truth_dir``).
    """

    def __init__(self, tmp: Path, model: Path, env: dict[str, str], *, overrides: dict[str, dict] | None = None,
                 remappings: dict[str, list[tuple[str, str]]] | None = None, extra: tuple = (),
                 hosts=None) -> None:
        from gsrmr_sim.sim_stack import environment, sim_stack
        from gsrmr_sim.supervisor import ProcessStack

        self.tmp = tmp
        self.link = str(tmp / "limo_pty")
        size = {"width": WIDTH, "height": HEIGHT}
        over: dict[str, dict] = {"gsrmr_mock_camera": dict(size),  # the server renders at its camera_info
                                 "gsrmr_scheduler": {"horizon": 60, "replan_period_s": 1.0},
                                 # the route never ends here (laps 0), so the server never pauses: a short queue
                                 # makes the scorer score from 30 waiting slots on (400 by default: 30 s)
                                 "gsrmr_sim_scorer": {"queue_slots": 40}}
        for name, params in (overrides or {}).items():
            over.setdefault(name, {}).update(params)
        self.specs = {s.name: s for s in sim_stack(
            model_path=str(model), record_dir=str(tmp / "rec"), link_path=self.link, laps=0,
            state_dir=str(tmp / "sched_state"), overrides=over,
            truth_dir=str(tmp / "truth_frames") if hosts is not None else "")}
        for name, remaps in (remappings or {}).items():
            self.specs[name].remappings.extend(remaps)
        for spec in extra:
            self.specs[spec.name] = spec
        # tests kill nodes with -9: environment(kill_safe=True)
        self.processes = ProcessStack(environment(base=env, kill_safe=True), tmp, params_dir=tmp / "params")
        self.env = self.processes.env
        self.procs = self.processes.procs
        self.hosts = hosts

    def start(self, name: str) -> subprocess.Popen:
        spec = self.specs[name]
        placement = {}
        if self.hosts is not None:
            ns = self.hosts.robot_ns if spec.host == "robot" else self.hosts.server_ns
            placement = {"prefix": ["ip", "netns", "exec", ns], "env": self.hosts.environment(self.env)}
        return self.processes.start(name, spec, wait_for_path=self.link if name == "gsrmr_mock_limo" else None,
                                    **placement)

    def start_all(self) -> None:
        for name in self.specs:
            self.start(name)

    def log(self, name: str) -> str:
        return self.processes.log(name)

    def kill9(self, name: str) -> None:
        """SIGKILL a node's process group and reap it."""
        self.processes.kill9(name)

    def stop(self) -> dict[str, float]:
        """SIGINT every process; seconds each took to exit."""
        return self.processes.stop()


@contextlib.contextmanager
def ros_client(env: dict[str, str], name: str = "test_client") -> Iterator[tuple]:
    """An rclpy node and a SingleThreadedExecutor in the ROS domain of ``env`` (its own context)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    old = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE",
                                          "FASTDDS_BUILTIN_TRANSPORTS")}
    os.environ.update({k: env[k] for k in old if k in env})
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node(name, context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        yield node, ex
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def spin_until(ex, predicate, timeout_s: float) -> bool:
    """Spin ``ex`` until ``predicate()`` is true or ``timeout_s`` passed; return whether it became true."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.05)
        if predicate():
            return True
    return False


def call_service(ex, client, request, timeout_s: float = 30.0, attempt_s: float = 5.0):
    """Call ``client`` with ``request``, resending every ``attempt_s`` until answered; the response.

    Only for idempotent requests (e.g. set_parameters). After a server process is killed with -9 and
    restarted, DDS discovery keeps the dead server's endpoints until their lease expires, so
    ``wait_for_service`` can succeed while the first request reaches only the dead endpoint and is
    never answered; a resend reaches the restarted server once it is matched.
    """
    deadline = time.monotonic() + timeout_s
    attempts = 0
    while time.monotonic() < deadline:
        attempts += 1
        future = client.call_async(request)
        if spin_until(ex, future.done, min(attempt_s, max(0.0, deadline - time.monotonic()))):
            return future.result()
        client.remove_pending_request(future)
    raise AssertionError(f"{client.srv_name}: no answer in {timeout_s} s ({attempts} attempts)")


def slot_rows(record_dir: Path) -> list[dict]:
    """Rows of ``record_dir/slots.csv`` (empty until the server wrote one)."""
    from gsrmr_server.recording import read_slots_csv

    path = Path(record_dir) / "slots.csv"
    if not path.exists() or path.stat().st_size == 0:  # created, header not written yet
        return []
    return read_slots_csv(path)
