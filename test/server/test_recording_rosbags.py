"""The run's MCAP read back by ``rosbags``, a reader this project did not write.

rosbags parses the ``ros2msg`` definitions embedded in the MCAP schemas itself (``AnyReader``) and also
ships the Kilted message types (``Stores.ROS2_KILTED``). Both must decode every message of every topic
to the values that were written, and the embedded definitions must describe the same fields as
Kilted's own (a wrong or truncated definition would decode garbage or fail). The first test records a
synthetic run with :class:`~gsrmr_server.recording.RunRecorder` (segments rotating, the way
``test_recording.py`` records); the second records a real one: robot and server processes over DDS,
the camera calibration relayed by the robot (latched) to a server started after it.
"""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path
import sys
import time

from nav_msgs.msg import Odometry
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Nodetype
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from std_msgs.msg import Float64MultiArray

from gsrmr_common import ros_wire, wire
from gsrmr_common.camera import Intrinsics
from gsrmr_common.jpeg import decode_jpeg
from gsrmr_common.slot_clock import SlotClock
from gsrmr_common.wire import LEDGER_FIELDS
from gsrmr_server import recording as rec
from gsrmr_server.recording import RunRecorder, read_slots_csv

sys.path.insert(0, str(Path(__file__).parents[1]))
from support.stack_harness import HEIGHT, WIDTH, make_point_model, ros_client, spin_until

CLOCK = SlotClock(0.1)
SLOT_NS = CLOCK.slot_len_ns
T0_SLOT = 17_638_000_000
N_SLOTS = 11
TOPIC_POSE_KEY = "/gsrmr/pose_key"
TOPIC_SCHEDULE = "/gsrmr/schedule"
TOPIC_LEDGER = "/gsrmr/ledger"
TOPIC_ODOM = "/gsrmr/odom"
KILTED = get_typestore(Stores.ROS2_KILTED)


def make_row(k: int) -> dict:
    slot = T0_SLOT + k
    return {"slot": slot, "stamp_s": CLOCK.start_ns(slot) / 1e9, "x": k % 2,
            "power_w": 0.05 + 0.01 * k, "bytes_sent": 24 if k % 2 == 0 else 15_000 + k, "energy_j": 1e-3 * (k + 1),
            "loss": 0.1 / (k + 1), "psnr_db": 20.0 + k, "ssim": 0.9, "source": ("render", "image", "fallback")[k % 3],
            "pose_a_m": 0.1 * k, "pose_b_m": -0.2 * k, "pose_theta_rad": math.pi / 7 * k, "latency_ms": 12.5,
            "faults": "" if k % 4 else "late;retry", "gs_loss": 0.02 * k if k % 2 else None,
            "energy_upload_all_j": 0.5 + k, "channel_gain": 1e-6 * (k + 1), "energy_image_j": 0.4 + k,
            "energy_key_j": 1e-3 * k, "gs_truth_loss": 0.03, "image_truth_loss": 0.01, "scored": k % 2,
            "round_slot": k - 1, "held_back": 0, "uplink_rate_bps": 2e6, "scene_change": int(k == 2),
            "frame_stamp_s": CLOCK.start_ns(slot) / 1e9 - 0.04, "correction_seq": k // 2, "level": k % 3,
            "time_left_ms": 65.0 - k, "predicted_ms": 19.5 + k, "compose_ms": 20.75 + k}


def make_image(k: int) -> np.ndarray:
    img = np.zeros((24, 32, 3), np.uint8)
    img[:, : 2 + k % 30] = (220, 30, 20)
    return img


def make_odom(k: int) -> Odometry:
    msg = Odometry()
    msg.header.stamp = ros_wire.ns_to_stamp(CLOCK.start_ns(T0_SLOT + k))
    msg.header.frame_id, msg.child_frame_id = "odom", "base_link"
    msg.pose.pose.position.x, msg.pose.pose.position.y = 0.5 * k, -0.25 * k
    msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = math.sin(0.05 * k), math.cos(0.05 * k)
    msg.pose.covariance = np.diag([0.01 * (k + 1)] * 6).reshape(-1).tolist()  # float64[36]: numpy in rclpy
    msg.twist.twist.angular.z = 0.1 * k
    return msg


def stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def nested_types(store, msgtype: str) -> set[str]:
    """``msgtype`` and every message type its fields use (rosbags field definitions, recursively)."""
    seen, todo = set(), [msgtype]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        for _, (kind, detail) in store.fielddefs[name][1]:
            inner = detail[0] if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE) else (kind, detail)
            if inner[0] == Nodetype.NAME:  # a nested message
                todo.append(inner[1])
    return seen


def read_everything(path: Path) -> tuple[dict[str, list[tuple[int, object]]], dict[str, str]]:
    """Decode every message of every topic twice (embedded definitions; rosbags' Kilted store).

    Returns {topic: [(log_time_ns, message decoded from the embedded definitions)]} and {topic: type};
    asserts the two decodings agree, re-encode to the recorded bytes, and that the embedded definitions
    equal Kilted's for each type and every nested type.
    """
    by_topic: dict[str, list[tuple[int, object]]] = {}
    types: dict[str, str] = {}
    with AnyReader([path]) as reader:  # no default_typestore: it must take the MCAP's own definitions
        for conn in reader.connections:
            types[conn.topic] = conn.msgtype
            assert conn.msgdef.data, conn.topic
            for name in nested_types(reader.typestore, conn.msgtype):
                assert reader.typestore.fielddefs[name] == KILTED.fielddefs[name], name
        for conn, log_time, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            assert bytes(reader.typestore.serialize_cdr(msg, conn.msgtype)) == bytes(raw), conn.topic
            by_topic.setdefault(conn.topic, []).append((log_time, msg))
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert {t: len(v) for t, v in by_topic.items()} == counts  # the summary's counts are what was read
    with Reader(path) as plain:  # the rosbag2 storage reader, decoded with the stock Kilted types
        decoded: dict[str, list] = {}
        for conn, log_time, raw in plain.messages():
            decoded.setdefault(conn.topic, []).append((log_time, KILTED.deserialize_cdr(raw, conn.msgtype)))
    assert set(decoded) == set(by_topic)
    for topic, items in decoded.items():
        assert [t for t, _ in items] == [t for t, _ in by_topic[topic]]
        for (_, a), (_, b) in zip(items, by_topic[topic], strict=True):
            assert repr(a) == repr(b), topic
    return by_topic, types


def test_synthetic_run_decodes_with_rosbags(tmp_path: Path) -> None:
    info = ros_wire.camera_info_from_intrinsics(Intrinsics.from_fov(160, 120, math.radians(70)), 5,
                                                "camera_optical_frame")
    schedule = wire.ScheduleMsg(T0_SLOT, 0.1, 3, np.array([1, 0, 0], np.int8), np.array([0.1, 0.02, 0.02]))
    t0 = CLOCK.start_ns(T0_SLOT)
    with RunRecorder(tmp_path, segment_slots=4) as recorder:
        recorder.write_message(rec.TOPIC_CAMERA_INFO, info, t0 - 1)
        recorder.write_message(TOPIC_SCHEDULE, ros_wire.schedule_to_msg(schedule), t0)
        for k in range(N_SLOTS):
            start = CLOCK.start_ns(T0_SLOT + k)
            key = wire.PoseKey(T0_SLOT + k, 0.1 * k, -0.2 * k, 0.3)
            recorder.write_message(TOPIC_POSE_KEY, ros_wire.pose_key_to_msg(key, CLOCK), start)
            recorder.write_message(TOPIC_LEDGER, Float64MultiArray(data=[float(T0_SLOT + k)] + [0.5 * k] * (
                len(LEDGER_FIELDS) - 1)), start)
            if k % 3 == 0:
                recorder.write_message(TOPIC_ODOM, make_odom(k), start)
            recorder.write_slot(make_row(k), make_image(k) if k != 3 else None,
                                (0.1 * k, -0.05 * k) if k != 4 else None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap", "slots.csv"]

    by_topic, types = read_everything(tmp_path / "run.mcap")
    array = "std_msgs/msg/Float64MultiArray"
    assert types == {rec.TOPIC_CAMERA_INFO: "sensor_msgs/msg/CameraInfo", TOPIC_ODOM: "nav_msgs/msg/Odometry",
                     TOPIC_POSE_KEY: "geometry_msgs/msg/Vector3Stamped", TOPIC_SCHEDULE: array, TOPIC_LEDGER: array,
                     **rec.TOPIC_TYPES}
    counts = {t: len(v) for t, v in by_topic.items()}
    assert counts == {rec.TOPIC_CAMERA_INFO: 1, TOPIC_SCHEDULE: 1, TOPIC_POSE_KEY: N_SLOTS, TOPIC_LEDGER: N_SLOTS,
                      TOPIC_ODOM: 4, rec.TOPIC_SLOT_LOG: N_SLOTS, rec.TOPIC_MR_IMAGE: N_SLOTS - 1,
                      rec.TOPIC_CMD_VEL: N_SLOTS - 1}

    ((log_time, got_info),) = by_topic[rec.TOPIC_CAMERA_INFO]
    assert log_time == t0 - 1 and stamp_ns(got_info.header.stamp) == 5
    assert (got_info.width, got_info.height, got_info.distortion_model) == (160, 120, "plumb_bob")
    assert got_info.header.frame_id == "camera_optical_frame"
    np.testing.assert_array_equal(got_info.k, info.k)
    np.testing.assert_array_equal(got_info.p, info.p)
    np.testing.assert_array_equal(got_info.d, np.zeros(5))

    ((_, got_sched),) = by_topic[TOPIC_SCHEDULE]
    assert [d.label for d in got_sched.layout.dim] == list(ros_wire.SCHEDULE_LABELS)
    np.testing.assert_array_equal(got_sched.data, schedule.to_data())

    rows = [make_row(k) for k in range(N_SLOTS)]
    for (log_time, log), row in zip(by_topic[rec.TOPIC_SLOT_LOG], rows, strict=True):
        assert log_time == CLOCK.start_ns(row["slot"])
        assert json.loads(log.data) == {**row, "faults": row["faults"] or None}
    for k, (log_time, key) in enumerate(by_topic[TOPIC_POSE_KEY]):
        assert key.header.frame_id == "map" and stamp_ns(key.header.stamp) == log_time
        assert (key.vector.x, key.vector.y, key.vector.z) == pytest.approx((0.1 * k, -0.2 * k, 0.3))
    for k, (_, led) in enumerate(by_topic[TOPIC_LEDGER]):
        assert len(led.data) == len(LEDGER_FIELDS) and led.data[0] == T0_SLOT + k and led.data[-1] == 0.5 * k
    for (_, odom), k in zip(by_topic[TOPIC_ODOM], (0, 3, 6, 9), strict=True):
        assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "base_link")
        assert odom.pose.pose.position.x == 0.5 * k and odom.twist.twist.angular.z == pytest.approx(0.1 * k)
        np.testing.assert_array_equal(odom.pose.covariance, make_odom(k).pose.covariance)
    for (log_time, img), k in zip(by_topic[rec.TOPIC_MR_IMAGE], [k for k in range(N_SLOTS) if k != 3], strict=True):
        assert img.format == wire.JPEG_FORMAT and stamp_ns(img.header.stamp) == log_time
        assert np.abs(decode_jpeg(bytes(img.data), expected_shape=(24, 32)).astype(int) - make_image(k)).mean() < 4
    for (_, cmd), k in zip(by_topic[rec.TOPIC_CMD_VEL], [k for k in range(N_SLOTS) if k != 4], strict=True):
        assert cmd.header.frame_id == "base_link"
        assert (cmd.twist.linear.x, cmd.twist.angular.z) == pytest.approx((0.1 * k, -0.05 * k))


def test_message_definitions_of_recorded_types_match_kilted() -> None:
    """Every type the project records: the embedded definition parses to Kilted's fields, nested ones too."""
    from rosbags.typesys import get_types_from_msg

    for type_name in sorted({*rec.TOPIC_TYPES.values(), "sensor_msgs/msg/CameraInfo", "nav_msgs/msg/Odometry",
                             "geometry_msgs/msg/Vector3Stamped", "std_msgs/msg/Float64MultiArray",
                             "geometry_msgs/msg/TwistStamped"}):
        store = get_typestore(Stores.EMPTY)
        store.register(get_types_from_msg(rec.message_definition(type_name), type_name))
        for name in nested_types(store, type_name):
            assert store.fielddefs[name] == KILTED.fielddefs[name], name
    # and the check bites: a definition missing a field does not match
    store = get_typestore(Stores.EMPTY)
    broken = rec.message_definition("geometry_msgs/msg/TwistStamped").replace("Twist twist\n", "")
    store.register(get_types_from_msg(broken, "geometry_msgs/msg/TwistStamped"))
    assert store.fielddefs["geometry_msgs/msg/TwistStamped"] != KILTED.fielddefs["geometry_msgs/msg/TwistStamped"]


def test_recorded_numpy_fields_decode_with_rclpy_too(tmp_path: Path) -> None:
    """Messages with fixed-size arrays (numpy in rclpy) are recorded and read back by ROS's own typesupport.

    (Bytes are not compared with rclpy's serializer: it leaves CDR padding bytes uninitialised.)
    """
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import CameraInfo

    info = ros_wire.camera_info_from_intrinsics(Intrinsics.from_fov(64, 48, 1.0), 7, "camera_optical_frame")
    info.d = [0.1, -0.02, 0.0, 0.001, 0.0]
    info.roi.width, info.roi.do_rectify = 32, True
    with RunRecorder(tmp_path) as recorder:
        recorder.write_message(rec.TOPIC_CAMERA_INFO, info, 7)
        recorder.write_message(TOPIC_ODOM, make_odom(2), 8)
        recorder.write_slot(make_row(0), None, None)
    with Reader(tmp_path / "run.mcap") as plain:
        raw = {c.topic: bytes(data) for c, _, data in plain.messages()}
    assert deserialize_message(raw[rec.TOPIC_CAMERA_INFO], CameraInfo) == info
    assert deserialize_message(raw[TOPIC_ODOM], Odometry) == make_odom(2)


# ------------------------------------------------------------------------ a real run over DDS

def _count(text: str, needle: str) -> int:
    return text.count(needle)


@pytest.mark.ros
def test_real_run_camera_info_relayed_latched_to_a_late_server_which_renders_with_it(ros_processes,
                                                                                    tmp_path: Path) -> None:
    """Robot relays camera_info (latched); a server started afterwards gets it, renders at its size, adopts a
    new calibration when the robot relays one, and records both."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import CameraInfo

    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    render_k = Intrinsics.from_fov(WIDTH, HEIGHT, math.radians(70))
    first = ros_wire.camera_info_from_intrinsics(Intrinsics.from_fov(320, 240, math.radians(90)), 0,
                                                 "camera_optical_frame")
    right = ros_wire.camera_info_from_intrinsics(render_k, 0, "camera_optical_frame")
    model = make_point_model(tmp_path, n=500)
    record_dir = tmp_path / "rec"
    relay_line = "camera_info → uplink/camera_info"

    robot = ros_processes.start("gsrmr-robot")
    ros_processes.wait_for(robot, "robot uplink:", timeout_s=30)
    with ros_client(ros_processes.env, "test_camera_info") as (node, ex):
        pub = node.create_publisher(CameraInfo, "camera/camera_info", qos_profile_sensor_data)

        def publish_until(msg: CameraInfo, relays: int) -> None:
            deadline = time.monotonic() + 30
            while _count("".join(ros_processes.output(robot)), relay_line) < relays:
                assert time.monotonic() < deadline, ros_processes.output(robot)
                msg.header.stamp = node.get_clock().now().to_msg()
                pub.publish(msg)
                ex.spin_once(timeout_sec=0.05)

        publish_until(first, 1)
        for _ in range(10):  # the same calibration with new stamps is not a change: no re-publish
            first.header.stamp = node.get_clock().now().to_msg()
            pub.publish(first)
            ex.spin_once(timeout_sec=0.05)
        # Nobody published camera/camera_info from here on; subscribers that join now get the latched copy.
        late: list[CameraInfo] = []
        node.create_subscription(CameraInfo, "uplink/camera_info", late.append, latched)
        assert spin_until(ex, lambda: bool(late), 15), "late subscriber got no latched camera_info"
        assert (late[0].width, late[0].height) == (320, 240)
        np.testing.assert_array_equal(late[0].k, first.k)
        assert _count("".join(ros_processes.output(robot)), relay_line) == 1

        server = ros_processes.start(
            "gsrmr-server", "--ros-args", "-p", f"model_path:={model}", "-p", "mr_content:=sandbox",
            "-p", f"record_dir:={record_dir}")
        statuses: list = []
        node.create_subscription(DiagnosticArray, "/diagnostics",
                                 lambda m: statuses.extend(s for s in m.status if "MR composition" in s.name), 10)

        def server_camera_info() -> str | None:
            return next((kv.value for s in reversed(statuses) for kv in s.values if kv.key == "camera_info"), None)

        ros_processes.wait_for(server, "render intrinsics from camera_info: 320×240", timeout_s=90)
        assert spin_until(ex, lambda: (server_camera_info() or "").startswith("320×240"), 20), statuses[-1:]
        assert not any("camera_info" in s.message for s in statuses[-1:]), statuses[-1:]  # no camera_info problem
        assert spin_until(ex, lambda: len(read_slots_csv(record_dir / "slots.csv")) >= 3, 30)

        publish_until(right, 2)  # a new calibration is relayed at once and adopted
        assert spin_until(ex, lambda: (server_camera_info() or "").startswith(f"{WIDTH}×{HEIGHT}"), 20), \
            server_camera_info()
        n = len(read_slots_csv(record_dir / "slots.csv"))
        assert spin_until(ex, lambda: len(read_slots_csv(record_dir / "slots.csv")) >= n + 3, 30)
    server_out = "".join(ros_processes.output(server))
    assert _count(server_out, "render intrinsics from camera_info") == 2 and "(was 320×240" in server_out
    robot_out = "".join(ros_processes.output(robot))
    if importlib.util.find_spec("tf2_ros") is None:  # this venv: said once, at INFO
        assert _count(robot_out, "[INFO]") and _count(robot_out, "TF not published: tf2_ros does not import") == 1
    for proc in (server, robot):
        assert ros_processes.interrupt(proc, timeout_s=20) < 20 and proc.returncode == 0, ros_processes.output(proc)
        assert "Traceback" not in "".join(ros_processes.output(proc))

    by_topic, types = read_everything(record_dir / "run.mcap")
    assert types[rec.TOPIC_CAMERA_INFO] == "sensor_msgs/msg/CameraInfo"
    infos = [m for _, m in by_topic[rec.TOPIC_CAMERA_INFO]]
    assert [(m.width, m.height) for m in infos] == [(320, 240), (WIDTH, HEIGHT)]
    np.testing.assert_array_equal(infos[0].k, first.k)
    np.testing.assert_array_equal(infos[1].k, right.k)
    assert Intrinsics.from_ros_k(infos[1].k, WIDTH, HEIGHT) == render_k
    rows = read_slots_csv(record_dir / "slots.csv")
    logs = [json.loads(m.data) for _, m in by_topic[rec.TOPIC_SLOT_LOG]]
    assert len(logs) == len(rows) >= 5 and [r["slot"] for r in logs] == [r["slot"] for r in rows]
    images = by_topic[rec.TOPIC_MR_IMAGE]
    assert len(images) == len(rows)  # the server records m̂_t every slot
    shapes = []
    for log_time, img in images:
        assert stamp_ns(img.header.stamp) == log_time
        shapes.append(decode_jpeg(bytes(img.data)).shape)
    switch = shapes.index((HEIGHT, WIDTH, 3))  # rendered at the first calibration, then at the new one
    assert switch >= 3 and set(shapes[:switch]) == {(240, 320, 3)} and set(shapes[switch:]) == {(HEIGHT, WIDTH, 3)}
