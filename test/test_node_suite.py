"""Integration: the node suite as real processes over DDS on a short route of the sandbox.

One stack (mock LIMO on a pty, LIMO driver, mock camera, route follower, robot, server, scheduler) is
started from the same process list as ``sim.launch.py`` (:func:`gsrmr_server.sim_stack.sim_stack`) at
160×120 with a small GS model made from a few round-1 frames. The tests then check the image path, the
key path, replanning through the service, parameter rejection, and a server killed and restarted.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytestmark = [pytest.mark.ros, pytest.mark.slow]

WIDTH, HEIGHT = 160, 120


@pytest.fixture(scope="module")
def small_model(tmp_path_factory) -> Path:
    """A GS model of the sandbox from 12 round-1 frames (depth-initialised, briefly trained)."""
    from gsrmr_server.splatting.train import TrainConfig, Trainer
    from gsrmr_server.world.recorder import record_round1, with_resolution
    from gsrmr_server.world.scene import load_scene

    folder = tmp_path_factory.mktemp("model")
    scene = with_resolution(load_scene("sandbox"), WIDTH, HEIGHT)
    dataset = record_round1(scene, folder / "round1", frames=12)
    trainer = Trainer.from_dataset(dataset, TrainConfig(init_points=6000, sh_degree=0, iterations=60,
                                                        densify_from=10_000))
    model = trainer.train(progress=False)
    return model.save_ply(folder / "model.ply")


class Stack:
    """The simulated system as processes in one isolated ROS domain."""

    def __init__(self, tmp: Path, model: Path, env: dict[str, str]) -> None:
        from gsrmr_server.sim_stack import sim_stack

        self.tmp, self.env = tmp, env
        self.link = str(tmp / "limo_pty")
        size = {"width": WIDTH, "height": HEIGHT}
        self.specs = {s.name: s for s in sim_stack(
            model_path=str(model), record_dir=str(tmp / "rec"), link_path=self.link, laps=0,
            state_dir=str(tmp / "sched_state"),
            overrides={"gsrmr_server": size, "gsrmr_mock_camera": size,
                       "gsrmr_scheduler": {"horizon": 60, "replan_period_s": 1.0}})}
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str) -> subprocess.Popen:
        from gsrmr_server.sim_stack import command_line

        argv = command_line(self.specs[name], Path(sys.executable).parent, self.tmp / "params")
        log = (self.tmp / f"{name}.log").open("a")
        proc = subprocess.Popen(argv, env=self.env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        self.procs[name] = proc
        return proc

    def start_all(self) -> None:
        for name in self.specs:
            self.start(name)
            if name == "gsrmr_mock_limo":
                deadline = time.monotonic() + 10
                while not os.path.exists(self.link) and time.monotonic() < deadline:
                    time.sleep(0.05)
                assert os.path.exists(self.link), self.log(name)[-2000:]

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.log").read_text()

    def stop(self) -> dict[str, float]:
        """SIGINT every process; seconds each took to exit."""
        took = {}
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for name, proc in self.procs.items():
            t0 = time.monotonic()
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            took[name] = time.monotonic() - t0
        return took


@pytest.fixture(scope="module")
def stack(small_model, tmp_path_factory):
    sys.path.insert(0, str(Path(__file__).parent))
    from conftest import ros_env

    tmp = tmp_path_factory.mktemp("stack")
    s = Stack(tmp, small_model, ros_env())
    s.start_all()
    try:
        yield s
    finally:
        s.stop()


@pytest.fixture(scope="module")
def client(stack):
    """An rclpy node in the stack's domain, for subscriptions and service calls from the test."""
    import rclpy
    from rclpy.context import Context

    old = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    os.environ.update({k: stack.env[k] for k in old})
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("test_node_suite", context=ctx)
    from rclpy.executors import SingleThreadedExecutor

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


def _spin_until(ex, predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.05)
        if predicate():
            return True
    return False


def _rows(stack) -> list[dict]:
    from gsrmr_server.recording import read_slots_csv

    path = stack.tmp / "rec" / "slots.csv"
    return read_slots_csv(path) if path.exists() else []


def test_mr_images_flow_through_image_and_key_paths(stack, client):
    from sensor_msgs.msg import Image

    node, ex = client
    frames: list[Image] = []
    node.create_subscription(Image, "mr/image", frames.append, 10)
    assert _spin_until(ex, lambda: len(frames) >= 20, 90), "no MR images: " + stack.log("gsrmr_server")[-2000:]
    img = frames[-1]
    assert (img.width, img.height, img.encoding) == (WIDTH, HEIGHT, "rgb8")
    # Wait until both paths were used: some slots carried the image, some only the pose key.
    assert _spin_until(ex, lambda: {"image", "render"} <= {r["source"] for r in _rows(stack)}, 60), \
        [r["source"] for r in _rows(stack)][-30:]
    rows = [r for r in _rows(stack) if r["bytes_sent"] is not None]  # slots whose ledger row arrived
    assert rows, "no ledger rows reached the server"
    for r in rows:
        assert r["energy_j"] is not None and r["energy_j"] > 0
        assert r["loss"] is None or 0 <= r["loss"] < 1
    image_rows = [r for r in rows if r["source"] == "image"]
    key_rows = [r for r in rows if r["source"] == "render"]
    assert all(r["bytes_sent"] > 1000 for r in image_rows)  # a JPEG + the key
    assert all(r["bytes_sent"] == 24 for r in key_rows)  # the 192-bit key alone
    assert any(r["gs_loss"] is not None for r in image_rows)  # the server measured L_t


def test_replan_service_reports_and_changes_schedule(stack, client):
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    node, ex = client
    replan = node.create_client(Trigger, "gsrmr/replan")
    assert replan.wait_for_service(timeout_sec=30)

    def call(cli, req):
        fut = cli.call_async(req)
        assert _spin_until(ex, fut.done, 30)
        return fut.result()

    first = call(replan, Trigger.Request())
    for key in ("method=", "T=", "images=", "energy_j=", "solve_time_s=", "changed_slots="):
        assert key in first.message, first.message
    setp = node.create_client(SetParameters, "gsrmr_scheduler/set_parameters")
    assert setp.wait_for_service(timeout_sec=10)
    # L_th = 0: every slot must carry its image, so the schedule changes wherever a key was planned.
    res = call(setp, SetParameters.Request(parameters=[Parameter("loss_threshold", value=0.0).to_parameter_msg()]))
    assert res.results[0].successful
    reply = call(replan, Trigger.Request())
    n_images = int(reply.message.split("images=")[1].split()[0])
    horizon = int(reply.message.split("T=")[1].split()[0])
    assert n_images == horizon, reply.message
    res = call(setp, SetParameters.Request(parameters=[Parameter("loss_threshold", value=0.5).to_parameter_msg()]))
    assert res.results[0].successful
    reply = call(replan, Trigger.Request())
    changed = int(reply.message.split("changed_slots=")[1].split(";")[0])
    assert changed > 0 and "switched" in reply.message, reply.message
    assert int(reply.message.split("images=")[1].split()[0]) < horizon


def test_out_of_range_and_unknown_parameters_are_refused(stack, client):
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    node, ex = client
    setp = node.create_client(SetParameters, "gsrmr_scheduler/set_parameters")
    assert setp.wait_for_service(timeout_sec=10)
    for name, value, reason in (("method", "bogus", "not one of"), ("loss_threshold", -0.5, ""),
                                ("horizon", 0, ""), ("solver_options", "{not json", "JSON")):
        fut = setp.call_async(SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()]))
        assert _spin_until(ex, fut.done, 20)
        result = fut.result().results[0]
        assert not result.successful, (name, value)
        assert reason in result.reason
    setr = node.create_client(SetParameters, "gsrmr_robot/set_parameters")
    assert setr.wait_for_service(timeout_sec=10)
    fut = setr.call_async(SetParameters.Request(parameters=[Parameter("jpeg_quality", value=500).to_parameter_msg()]))
    assert _spin_until(ex, fut.done, 20)
    assert not fut.result().results[0].successful


def test_server_killed_and_restarted_mid_run(stack, client):
    from sensor_msgs.msg import Image

    node, ex = client
    frames: list[int] = []
    node.create_subscription(Image, "mr/image", lambda m: frames.append(m.header.stamp.sec), 10)
    assert _spin_until(ex, lambda: len(frames) >= 5, 30)
    rows_before = len(_rows(stack))
    stack.procs["gsrmr_server"].send_signal(signal.SIGKILL)
    stack.procs["gsrmr_server"].wait(timeout=10)
    time.sleep(1.0)
    # The others carry on: the robot keeps uploading, the scheduler keeps planning.
    for name in ("gsrmr_robot", "gsrmr_scheduler", "gsrmr_mock_camera", "gsrmr_limo_base"):
        assert stack.procs[name].poll() is None, name
    # The recorder lost no slot it had written before the crash (flushed per row).
    from gsrmr_server.recording import read_slots_csv

    assert len(read_slots_csv(stack.tmp / "rec" / "slots.csv")) >= rows_before
    # Restart into a fresh record dir; MR images resume.
    stack.specs["gsrmr_server"].params["record_dir"] = str(stack.tmp / "rec2")
    stack.start("gsrmr_server")
    frames.clear()
    assert _spin_until(ex, lambda: len(frames) >= 10, 90), stack.log("gsrmr_server")[-2000:]


def test_every_process_exits_cleanly_on_sigint(stack):
    took = stack.stop()
    for name, proc in stack.procs.items():
        assert proc.returncode == 0, (name, proc.returncode, stack.log(name)[-1500:])
        assert took[name] < 15, name
    summary = json.loads((stack.tmp / "rec2" / "server_summary.json").read_text())
    assert summary["slots"] > 0
    assert np.isfinite(summary["slots_on_time"])
