"""A rogue participant for the hostile-graph suite: joins a running stack's ROS domain, lies with well-formed messages.

Every lie parses perfectly; what stops it is the nodes' own checks (``docs/security.md``, "Application checks").
The rogue is a node named :data:`ROGUE_NAME` (a stranger: no writer list names it) — or, for the impostor cases, a
node under a legitimate name. It watches ``/diagnostics`` while it lies and reports which nodes named it and what
each counted (:class:`DiagnosticsWatch`).

Cases (:data:`CASES`; the issue's list, each at the rate the issue names where it names one):

``loss_high`` / ``loss_zero``  loss samples of 5.0 / 0.0 at random poses, 20/s, on ``gsrmr/loss_sample``;
``schedule``  "an image in every slot at 50 mW, every gain threshold 0" on ``gsrmr/schedule`` (latched), 10/s,
    its seq far above the scheduler's;
``gain_high`` / ``gain_low``  the radio's channel gain of every slot ×1000 / ÷1000, right after the radio's;
``pose_jump``  pose keys across the room, every slot;
``image_replay``  the robot's first uploaded image again, stamped with the current slot, every slot;
``ledger``  a foreign ledger: every slot "image held back, link at 1 kbit/s";
``camera_info``  a rogue ``uplink/camera_info`` (twice the focal length), latched;
``reader``  a reliable subscriber of the uploaded images that never acknowledges (a child process over UDP, stopped
    with SIGSTOP once the robot has matched it: its DDS threads send no acknowledgement; continued for 0.5 s every
    15 s, so its participant stays alive and matched; ``--reader-shm``: over the default transport, shared memory
    included);
``flood``  10 kHz on one topic (``--flood-topic``, default ``gsrmr/loss_sample``) for ``--flood-s`` (3 s);
``params``  ``set_parameters`` from a stranger — admitting itself to a writer list, a live parameter of every
    deployment node — then ``gsrmr/replan`` 20 times a second;
``cmd_vel``  ``cmd_vel`` at full speed (1 m/s, 1 rad/s), 20/s, while the route follower drives;
``impostor_loss``  loss samples of 5.0 from a node named ``gsrmr_server`` (the right name: detected, not refused).

CLI (the bench's rogue process): ``python test/support/hostile.py CASE --duration-s S --out result.json`` in the
domain of ``ROS_DOMAIN_ID``; SIGINT/SIGTERM end it early (the result is written either way).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import contextlib
import json
import math
import os
from pathlib import Path
import signal
import subprocess
import sys
import time
from typing import Any

import numpy as np

ROGUE_NAME = "gsrmr_hostile"
READER_NAME = "gsrmr_hostile_reader"
SLOT_NS = 100_000_000
CASES = ("loss_high", "loss_zero", "schedule", "gain_high", "gain_low", "pose_jump", "image_replay", "ledger",
         "camera_info", "reader", "flood", "params", "cmd_vel", "impostor_loss")
#: The node a case's lie targets (the one that must name the rogue on /diagnostics).
TARGETS = {"loss_high": ("gsrmr_scheduler",), "loss_zero": ("gsrmr_scheduler",),
           "schedule": ("gsrmr_robot", "gsrmr_server"), "gain_high": ("gsrmr_robot",), "gain_low": ("gsrmr_robot",),
           "pose_jump": ("gsrmr_server", "gsrmr_scheduler"), "image_replay": ("gsrmr_server",),
           "ledger": ("gsrmr_server", "gsrmr_scheduler"), "camera_info": ("gsrmr_server",), "reader": ("gsrmr_robot",),
           "flood": ("gsrmr_scheduler",), "params": (), "cmd_vel": ("gsrmr_limo_base",),
           "impostor_loss": ("gsrmr_scheduler",)}
DEPLOYMENT_NODES = ("gsrmr_robot", "gsrmr_server", "gsrmr_scheduler", "gsrmr_limo_base")


class DiagnosticsWatch:
    """The latest ``/diagnostics`` status of every node (by the name before ``:``), and who mentions a name."""

    def __init__(self, node: Any) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        self.latest: dict[str, dict[str, str]] = {}
        self.messages: dict[str, str] = {}
        self.mentions: dict[str, set[str]] = {}  # name looked for → nodes whose status named it (ever)
        self._wanted: tuple[str, ...] = ()
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 50)

    def look_for(self, *names: str) -> None:
        """Remember every node whose status ever mentions one of ``names`` (message or values)."""
        self._wanted = names

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            node = st.name.split(":")[0]
            values = {kv.key: kv.value for kv in st.values}
            self.latest[node], self.messages[node] = values, st.message
            text = st.message + " " + " ".join(values.values())
            for name in self._wanted:
                if name in text:
                    self.mentions.setdefault(name, set()).add(node)

    def named_by(self, name: str) -> list[str]:
        """The nodes that named ``name`` on /diagnostics so far."""
        return sorted(self.mentions.get(name, set()))

    def counters(self, node: str) -> dict[str, Any]:
        """What ``node`` counted: its refused writers, implausible inputs, parameter refusals and alarms (JSON)."""
        values = self.latest.get(node, {})
        out = {}
        for key in ("writers_refused", "implausible", "writer_alarms", "parameter_changes",
                    "parameter_changes_refused", "replans_refused", "image_readers_unknown",
                    "images_delivered_by_model", "schedule_seq", "floods", "loss_samples_unverified",
                    "loss_samples_redelivered"):
            if key in values:
                with contextlib.suppress(ValueError):
                    out[key] = json.loads(values[key])
                    continue
                out[key] = values[key]
        return out


class Rogue:
    """The lies of :data:`CASES` from ``node`` (its executor ``ex``); each case runs for ``duration_s``."""

    def __init__(self, node: Any, ex: Any, *, stop: Callable[[], bool] = lambda: False,
                 watch: DiagnosticsWatch | None = None) -> None:
        self.node, self.ex, self.stop, self.watch = node, ex, stop, watch
        self.reader_udp = True  # the reader case's child over UDP (False: the default transport, shared memory too)
        self.rng = np.random.default_rng(28)
        self.sent = 0
        self.notes: dict[str, Any] = {}

    # ------------------------------------------------------------------ helpers
    def now_slot(self) -> int:
        return self.node.get_clock().now().nanoseconds // SLOT_NS

    def _loop(self, duration_s: float, period_s: float, step: Callable[[], None]) -> None:
        """Call ``step`` every ``period_s`` for ``duration_s`` (spinning in between)."""
        end = time.monotonic() + duration_s
        next_t = time.monotonic()
        while time.monotonic() < end and not self.stop():
            if time.monotonic() >= next_t:
                step()
                next_t += period_s
            self.ex.spin_once(timeout_sec=min(0.01, max(0.0, next_t - time.monotonic())))

    def _publisher(self, kind: type, topic: str, qos: Any = 10) -> Any:
        pub = self.node.create_publisher(kind, topic, qos)
        end = time.monotonic() + 3.0
        while pub.get_subscription_count() == 0 and time.monotonic() < end:  # discovery, so no lie is lost
            self.ex.spin_once(timeout_sec=0.05)
        return pub

    def run(self, case: str, duration_s: float, **options: Any) -> dict[str, Any]:
        """Lie as ``case`` says for ``duration_s``; what was sent and noticed."""
        getattr(self, f"case_{case}")(duration_s, **options)
        return {"case": case, "sent": self.sent, **self.notes}

    # ------------------------------------------------------------------ cases
    def _loss_samples(self, duration_s: float, loss: float) -> None:
        from std_msgs.msg import Float64MultiArray

        from gsrmr_common.ros_wire import LOSS_SAMPLE_QOS, loss_sample_to_msg
        from gsrmr_common.wire import LossSample

        pub = self._publisher(Float64MultiArray, "gsrmr/loss_sample", LOSS_SAMPLE_QOS)  # the QoS the graph shows

        def step() -> None:
            a, b = self.rng.uniform(-4, 4, 2)
            pub.publish(loss_sample_to_msg(LossSample(self.now_slot(), float(a), float(b),
                                                      float(self.rng.uniform(-math.pi, math.pi)), loss)))
            self.sent += 1

        self._loop(duration_s, 0.05, step)

    def case_loss_high(self, duration_s: float) -> None:
        self._loss_samples(duration_s, 5.0)

    def case_loss_zero(self, duration_s: float) -> None:
        self._loss_samples(duration_s, 0.0)

    def case_impostor_loss(self, duration_s: float) -> None:
        self._loss_samples(duration_s, 5.0)

    def case_schedule(self, duration_s: float) -> None:
        from std_msgs.msg import Float64MultiArray

        from gsrmr_common.ros_wire import SCHEDULE_QOS, schedule_to_msg
        from gsrmr_common.wire import ScheduleMsg

        pub = self._publisher(Float64MultiArray, "gsrmr/schedule", SCHEDULE_QOS)
        n = 100

        def step() -> None:
            self.sent += 1
            pub.publish(schedule_to_msg(ScheduleMsg(self.now_slot() + 1, 0.1, 1_000_000 + self.sent,
                                                    np.ones(n, np.int8), np.full(n, 0.05), np.zeros(n))))

        self._loop(duration_s, 0.1, step)

    def _gains(self, duration_s: float, factor: float) -> None:
        from std_msgs.msg import Float64MultiArray

        from gsrmr_common.ros_wire import channel_sample_from_msg, channel_sample_to_msg
        from gsrmr_common.wire import CHANNEL_TOPIC, ChannelSample

        pub = self._publisher(Float64MultiArray, CHANNEL_TOPIC, 10)
        lied: set[int] = set()

        def on_true(msg: Float64MultiArray) -> None:  # the first sample of a slot is the radio's: lie right after
            sample = channel_sample_from_msg(msg)
            if sample.slot in lied:
                return
            lied.add(sample.slot)
            pub.publish(channel_sample_to_msg(ChannelSample(sample.slot, sample.round_slot, sample.gain * factor)))
            self.sent += 1

        sub = self.node.create_subscription(Float64MultiArray, CHANNEL_TOPIC, on_true, 10)
        self._loop(duration_s, 1.0, lambda: None)
        self.node.destroy_subscription(sub)

    def case_gain_high(self, duration_s: float) -> None:
        self._gains(duration_s, 1000.0)

    def case_gain_low(self, duration_s: float) -> None:
        self._gains(duration_s, 1e-3)

    def case_pose_jump(self, duration_s: float) -> None:
        from geometry_msgs.msg import Vector3Stamped

        from gsrmr_common.ros_wire import UPLINK_QOS, pose_key_to_msg
        from gsrmr_common.slot_clock import SlotClock
        from gsrmr_common.wire import PoseKey

        pub = self._publisher(Vector3Stamped, "uplink/pose_key", UPLINK_QOS)
        clock = SlotClock(0.1)

        def step() -> None:
            a, b = self.rng.uniform(-5, 5, 2)
            pub.publish(pose_key_to_msg(PoseKey(self.now_slot(), float(a), float(b), 0.0), clock))
            self.sent += 1

        self._loop(duration_s, 0.1, step)

    def case_image_replay(self, duration_s: float) -> None:
        from sensor_msgs.msg import CompressedImage

        from gsrmr_common.ros_wire import IMAGE_UPLOAD_QOS, compressed_to_msg

        recorded: list[bytes] = []
        sub = self.node.create_subscription(CompressedImage, "uplink/image_raw/compressed",
                                            lambda m: recorded.append(bytes(m.data)) if not recorded else None,
                                            IMAGE_UPLOAD_QOS)
        end = time.monotonic() + 10.0
        while not recorded and time.monotonic() < end and not self.stop():
            self.ex.spin_once(timeout_sec=0.05)
        self.node.destroy_subscription(sub)
        self.notes["recorded_image"] = bool(recorded)
        if not recorded:
            return
        pub = self._publisher(CompressedImage, "uplink/image_raw/compressed", IMAGE_UPLOAD_QOS)

        def step() -> None:
            pub.publish(compressed_to_msg(recorded[0], (self.now_slot() + 1) * SLOT_NS, "camera_optical_frame"))
            self.sent += 1

        self._loop(duration_s, 0.1, step)

    def case_ledger(self, duration_s: float) -> None:
        from std_msgs.msg import Float64MultiArray

        from gsrmr_common.ros_wire import UPLINK_QOS, ledger_to_msg
        from gsrmr_common.wire import LedgerRow

        pub = self._publisher(Float64MultiArray, "gsrmr/ledger", UPLINK_QOS)

        def step() -> None:  # "image held back, the link carries 1 kbit/s": a plan would nearly stop sending images
            pub.publish(ledger_to_msg(LedgerRow(self.now_slot() + 1, 0, 1e-3, 192, 1e-6, 1e-6, 1e-7, 64_000, 1e-4,
                                                held_back=1, uplink_rate_bps=1e3)))
            self.sent += 1

        self._loop(duration_s, 0.1, step)

    def case_camera_info(self, duration_s: float) -> None:
        import math as m

        from sensor_msgs.msg import CameraInfo

        from gsrmr_common.camera import Intrinsics
        from gsrmr_common.ros_wire import CAMERA_INFO_QOS, camera_info_from_intrinsics

        pub = self._publisher(CameraInfo, "uplink/camera_info", CAMERA_INFO_QOS)
        wrong = Intrinsics.from_fov(320, 240, m.radians(35))  # about twice the focal length of the real one

        def step() -> None:
            pub.publish(camera_info_from_intrinsics(wrong, self.node.get_clock().now().nanoseconds,
                                                    "camera_optical_frame"))
            self.sent += 1

        self._loop(duration_s, 1.0, step)

    def case_reader(self, duration_s: float) -> None:
        # the reader talks UDP, as a participant on another machine does: a stopped process on this machine's shared
        # memory would freeze the Fast DDS transport of every writer that sends to it (its port no longer drains; the
        # dead-port case of docs/reliability.md) — a local attack no application check can answer (docs/security.md)
        env = {**os.environ, "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"} if self.reader_udp else os.environ.copy()
        child = subprocess.Popen([sys.executable, __file__, "--reader-child"], env=env,
                                 stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        try:
            ready = child.stdout.readline().strip() if child.stdout else ""
            self.notes["reader_ready"] = ready == "ready"
            # stopped before discovery has finished, the reader would never be matched with the robot's image writer
            # (endpoint discovery is itself a reliable exchange): wait until this node's graph shows it, then until the
            # robot names it on /diagnostics (a watch; a robot without that check — before issue 28 — gets 3 s)
            def in_graph() -> bool:
                return any(i.node_name == READER_NAME for i in
                           self.node.get_subscriptions_info_by_topic("uplink/image_raw/compressed"))

            def robot_named() -> bool | None:
                status = self.watch.latest.get("gsrmr_robot") if self.watch is not None else None
                if status is None or "image_readers_unknown" not in status:
                    return None
                return READER_NAME in status["image_readers_unknown"]

            end = time.monotonic() + 30.0
            while not in_graph() and time.monotonic() < end and not self.stop():
                self.ex.spin_once(timeout_sec=0.1)
            settle = time.monotonic() + 3.0
            while time.monotonic() < end and not self.stop():
                named = robot_named()
                if named or (named is None and time.monotonic() >= settle):
                    break
                self.ex.spin_once(timeout_sec=0.1)
            self.notes["reader_matched"] = in_graph() and robot_named() is not False
            self.notes["reader_named_by_robot"] = bool(robot_named())
            end = time.monotonic() + duration_s
            stops = 0
            while time.monotonic() < end and not self.stop():
                child.send_signal(signal.SIGSTOP)  # its DDS threads stop: no acknowledgement leaves it
                stops += 1
                self.notes.setdefault("stopped_at", time.time())
                self._loop(min(15.0, max(0.0, end - time.monotonic())), 1.0, lambda: None)
                child.send_signal(signal.SIGCONT)  # half a second alive: its participant's lease stays fresh
                self._loop(0.5, 0.5, lambda: None)
            self.sent = stops
        finally:
            with contextlib.suppress(ProcessLookupError):
                child.send_signal(signal.SIGCONT)
                child.send_signal(signal.SIGINT)
            try:
                child.wait(timeout=10)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()

    def case_flood(self, duration_s: float, flood_topic: str = "gsrmr/loss_sample", flood_s: float = 3.0,
                   rate_hz: float = 10_000.0) -> None:
        from std_msgs.msg import Float64MultiArray

        from gsrmr_common.ros_wire import LOSS_SAMPLE_QOS, UPLINK_QOS, loss_sample_to_msg
        from gsrmr_common.wire import LossSample

        # the QoS the graph shows for that topic (a volatile writer would not match the latched loss-sample reader)
        pub = self._publisher(Float64MultiArray, flood_topic,
                              LOSS_SAMPLE_QOS if flood_topic.endswith("gsrmr/loss_sample") else UPLINK_QOS)
        msg = loss_sample_to_msg(LossSample(self.now_slot(), 0.0, 0.0, 0.0, 0.5))
        wait_s = max(0.0, duration_s - flood_s) / 2
        self._loop(wait_s, 1.0, lambda: None)
        t0 = time.monotonic()
        period = 1.0 / rate_hz
        next_t = t0
        while time.monotonic() - t0 < flood_s and not self.stop():
            now = time.monotonic()
            if now >= next_t:
                pub.publish(msg)
                self.sent += 1
                next_t += period
                if next_t < now - 0.01:  # the publisher cannot keep up: do not burst to catch up
                    next_t = now
        self.notes["flood_hz"] = round(self.sent / max(1e-9, time.monotonic() - t0))
        self.notes["flood_topic"] = flood_topic
        self._loop(wait_s, 1.0, lambda: None)

    def case_params(self, duration_s: float) -> None:
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter
        from std_srvs.srv import Trigger

        attempts = [("gsrmr_robot", "schedule_writers", [ROGUE_NAME]), ("gsrmr_robot", "jpeg_quality", 1),
                    ("gsrmr_scheduler", "loss_threshold", 0.5), ("gsrmr_scheduler", "loss_writers", [ROGUE_NAME]),
                    ("gsrmr_server", "process_delay_s", 5.0), ("gsrmr_limo_base", "cmd_vel_writers", [ROGUE_NAME]),
                    ("gsrmr_limo_base", "motion_mode", "mecanum")]
        results = {}
        for node_name, name, value in attempts:
            client = self.node.create_client(SetParameters, f"{node_name}/set_parameters")
            if not client.wait_for_service(timeout_sec=5.0):
                results[f"{node_name}.{name}"] = "no service"
                continue
            future = client.call_async(SetParameters.Request(parameters=[Parameter(name, value=value)
                                                                         .to_parameter_msg()]))
            end = time.monotonic() + 10.0
            while not future.done() and time.monotonic() < end:
                self.ex.spin_once(timeout_sec=0.05)
            res = future.result().results[0] if future.done() else None
            results[f"{node_name}.{name}"] = ("no answer" if res is None else
                                              "CHANGED" if res.successful else f"refused: {res.reason}")
            self.sent += 1
        self.notes["set_parameters"] = results
        replan = self.node.create_client(Trigger, "gsrmr/replan")
        replan.wait_for_service(timeout_sec=5.0)
        answers = {"success": 0, "refused": 0}

        def step() -> None:
            future = replan.call_async(Trigger.Request())
            future.add_done_callback(lambda f: answers.__setitem__(
                "success" if f.result().success else "refused",
                answers["success" if f.result().success else "refused"] + 1))
            self.sent += 1

        self._loop(max(0.0, duration_s - 5.0), 0.05, step)
        self.notes["replan_answers"] = answers

    def case_cmd_vel(self, duration_s: float) -> None:
        from geometry_msgs.msg import Twist

        pub = self._publisher(Twist, "cmd_vel", 10)
        cmd = Twist()
        cmd.linear.x, cmd.angular.z = 1.0, 1.0

        def step() -> None:
            pub.publish(cmd)
            self.sent += 1

        self._loop(duration_s, 0.05, step)


def named_marker(rogue_name: str, case: str = "") -> str:
    """What /diagnostics says of the rogue: its name (a stranger; the reader case's child is a node of its own), or
    the alarm of two live endpoints under the name it borrowed (an impostor)."""
    if case == "reader":
        return READER_NAME
    return ROGUE_NAME if rogue_name == ROGUE_NAME else f"two live endpoints under /{rogue_name}"


def reader_child() -> int:
    """The never-acknowledging reader: a reliable subscription of the uploaded images in a process the parent
    stops with SIGSTOP (it prints ``ready`` once its subscription exists)."""
    import rclpy
    from sensor_msgs.msg import CompressedImage

    from gsrmr_common.ros_wire import IMAGE_UPLOAD_QOS

    rclpy.init()
    node = rclpy.create_node(READER_NAME)
    node.create_subscription(CompressedImage, "uplink/image_raw/compressed", lambda _m: None, IMAGE_UPLOAD_QOS)
    print("ready", flush=True)
    with contextlib.suppress(KeyboardInterrupt, Exception):
        rclpy.spin(node)
    return 0


def main(argv: list[str] | None = None) -> int:
    """The CLI of the module docstring."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", nargs="?", choices=CASES)
    ap.add_argument("--duration-s", type=float, default=20.0)
    ap.add_argument("--out", default="")
    ap.add_argument("--flood-topic", default="gsrmr/loss_sample")
    ap.add_argument("--reader-shm", action="store_true", help="reader case: the child on the default transport")
    ap.add_argument("--reader-child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.reader_child:
        return reader_child()
    if args.case is None:
        ap.error("a case is required")
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    stopped = {"flag": False}

    def on_signal(_signum: int, _frame: object) -> None:
        stopped["flag"] = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    name = "gsrmr_server" if args.case == "impostor_loss" else ROGUE_NAME
    node = rclpy.create_node(name)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    watch = DiagnosticsWatch(node)
    marker = named_marker(name, args.case)
    watch.look_for(marker)
    rogue = Rogue(node, ex, stop=lambda: stopped["flag"], watch=watch)
    rogue.reader_udp = not args.reader_shm
    options = {"flood_topic": args.flood_topic} if args.case == "flood" else {}
    t0 = time.monotonic()
    result = rogue.run(args.case, args.duration_s, **options)
    rogue._loop(2.5, 1.0, lambda: None)  # the nodes' next /diagnostics after the lie
    result.update({"seconds": round(time.monotonic() - t0, 1), "rogue": f"/{name}",
                   "named_by": watch.named_by(marker),
                   "counters": {n: watch.counters(n) for n in DEPLOYMENT_NODES}})
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1, default=str))
    print(json.dumps(result, default=str), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository root, for its packages
    sys.exit(main())
