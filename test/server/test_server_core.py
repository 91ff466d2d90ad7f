"""Tests of the server's uplink bookkeeping, the loss map, the wire formats, the server node's pure policy objects
(ledger book and expected image, render intrinsics from camera_info, the stats of /diagnostics and
server_summary.json) and a thin test of the node that wires them."""

from dataclasses import replace
import json
import math
from pathlib import Path
import threading
import time
from types import SimpleNamespace

from conftest import ros_env
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from support.stack_harness import make_point_model

from gsrmr_common.camera import Intrinsics
from gsrmr_common.ros_wire import camera_info_from_intrinsics, ledger_to_msg, mr_slot_info_from_msg
from gsrmr_common.tf_tree import CAMERA_OPTICAL_FRAME
from gsrmr_common.wire import LedgerRow, MRSlotInfo, PoseKey, RealSource, ScheduleMsg, UplinkFault
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_server.ledger_book import LedgerBook, SlotPlan
from gsrmr_server.render_intrinsics import WAITING, RenderIntrinsics, describe, intrinsics_mismatch
from gsrmr_server.server_node import ServerNode
from gsrmr_server.server_stats import ServerStats, diagnostic_report
from gsrmr_server.uplink import UplinkAssembler


def test_schedule_roundtrip_and_rejects_inconsistent_data():
    msg = ScheduleMsg(1_000_000_123, 0.1, 7, np.array([1, 0, 0, 1], np.int8), np.array([0.5, 1e-6, 0.0, 2.0]))
    back = ScheduleMsg.from_data(msg.to_data())
    assert back.first_slot == msg.first_slot and back.seq == 7 and back.slot_s == 0.1
    np.testing.assert_array_equal(back.x, msg.x)
    np.testing.assert_allclose(back.power_w, msg.power_w)
    assert back.lookup(1_000_000_124) == (0, pytest.approx(1e-6))
    assert back.lookup(1_000_000_122) is None and back.lookup(1_000_000_127) is None
    data = msg.to_data()
    for bad in (data[:-1], [*data[:4], 2.0, *data[5:]], [*data[:-1], -1.0], [*data[:1], float("nan"), *data[2:]]):
        with pytest.raises(ValueError):
            ScheduleMsg.from_data(bad)


def test_assembler_counts_every_fault_and_never_blocks():
    up = UplinkAssembler(max_future_slots=10)
    up.on_key(PoseKey(5, 1.0, 2.0, 0.1), now_slot=5, now_ns=0)
    up.on_key(PoseKey(5, 1.0, 2.0, 0.1), now_slot=5, now_ns=0)  # duplicate
    up.on_key(PoseKey(6, float("nan"), 2.0, 0.1), now_slot=6, now_ns=0)  # invalid
    up.on_image(5, b"jpeg", now_slot=5, now_ns=0)
    up.on_image(5, b"jpeg", now_slot=5, now_ns=0)  # duplicate
    up.on_key(PoseKey(500, 0.0, 0.0, 0.0), now_slot=6, now_ns=0)  # far future: forged or bad clock
    s5 = up.take(5, image_expected=True)
    assert s5.key == PoseKey(5, 1.0, 2.0, 0.1) and s5.jpeg == b"jpeg" and not s5.faults
    up.on_image(5, b"late", now_slot=6, now_ns=0)  # after its slot was taken
    s6 = up.take(6, image_expected=True)
    assert s6.key is None and s6.jpeg is None and set(s6.faults) == {"missing_key", "missing_image"}
    assert dict(up.faults) == {"duplicate_key": 1, "invalid_key": 1, "duplicate_image": 1, "future": 1,
                               "late": 1, "missing_key": 1, "missing_image": 1}


def test_best_pose_extrapolates_and_is_bounded():
    up = UplinkAssembler(max_extrapolation_slots=3)
    assert up.best_pose(0) is None
    up.on_key(PoseKey(10, 0.0, 0.0, 0.0), 10, 0)
    up.on_key(PoseKey(12, 0.2, 0.0, 0.1), 12, 0)
    est = up.best_pose(13)
    assert (est.a_m, est.theta_rad) == (pytest.approx(0.3), pytest.approx(0.15))
    far = up.best_pose(100)
    assert far.a_m == pytest.approx(0.5)  # at most 3 slots of extrapolation


def test_loss_map_learns_neighbours_prior_and_forgets():
    lm = LossMap(cell_m=0.5, heading_bins=4, radius_m=1.0, prior=0.07, forgetting=0.5)
    assert lm.predict(0.1, 0.1, 0.0) == 0.07
    lm.add(0.1, 0.1, 0.0, 0.02)
    assert lm.predict(0.2, 0.3, 0.1) == pytest.approx(0.02)  # same cell, same sector
    assert lm.predict(0.6, 0.1, 0.0) == pytest.approx(0.02)  # neighbour cell
    assert lm.predict(0.1, 0.1, math.pi) == 0.07  # facing the other way: no information
    assert lm.predict(5.0, 5.0, 0.0) == 0.07  # far away
    for _ in range(5):
        lm.add(0.1, 0.1, 0.0, 0.2)  # the world changed here
    assert lm.predict(0.1, 0.1, 0.0) > 0.19
    lm.add(0.1, 0.1, 0.0, float("nan"))
    back = LossMap.from_json(lm.to_json())
    assert back.predict_many(np.array([[0.1, 0.1, 0.0], [9, 9, 0]])) == pytest.approx([lm.predict(0.1, 0.1, 0), 0.07])


def _ledger(slot: int, x: int) -> LedgerRow:
    return LedgerRow(slot, x, 0.0, 192, 1e-6, 0.0, 0.0, 8000, 0.0)


def test_ledger_book_expects_what_the_robot_said_else_the_schedule_and_forgets_old_rows():
    book = LedgerBook(keep=3)
    book.schedule = ScheduleMsg(100, 0.1, 1, np.array([1, 0], np.int8), np.array([0.1, 1e-6]))
    assert book.image_sent(100) is None and book.take(100) == SlotPlan(None, 1)
    assert book.take(100).image_expected is True and book.take(101).image_expected is False
    assert book.take(102) == SlotPlan() and SlotPlan().image_expected is None  # no schedule covers it
    book.add(_ledger(101, 1))  # the robot decided in the slot: an image, whatever the schedule said
    assert book.image_sent(101) is True
    plan = book.take(101)
    assert plan.ledger == _ledger(101, 1) and plan.scheduled_x == 0 and plan.image_expected is True
    assert book.image_sent(101) is None  # taken
    for slot in (103, 104, 105, 106):
        book.add(_ledger(slot, 0))
    assert book.image_sent(103) is None and book.image_sent(106) is False  # the newest 3 kept
    with pytest.raises(ValueError):
        LedgerBook(keep=0)


def test_render_intrinsics_adopt_a_usable_calibration_and_refuse_an_unusable_one_once():
    small, large = Intrinsics.from_fov(32, 24, 1.2), Intrinsics.from_fov(48, 36, 1.0)
    camera = RenderIntrinsics()
    assert camera.intrinsics is None and camera.status == WAITING and camera.problems() == [WAITING]
    refused = camera.offer(None, "distortion")
    assert refused.level == "warning" and "no intrinsics yet" in refused.text
    assert camera.status == "unusable: distortion"
    assert camera.problems() == [WAITING, "camera_info refused"]
    first = camera.offer(small)
    assert first.level == "info" and first.text == f"render intrinsics from camera_info: {describe(small)}"
    assert camera.intrinsics == small and camera.status.startswith("32×24 fx=") and camera.problems() == []
    assert camera.offer(small) is None  # the same again: nothing to say
    change = camera.offer(large)
    assert camera.intrinsics == large and "(was 32×24" in change.text and "size 48×36 != 32×24" in change.text
    assert camera.offer(None, "skew").text.endswith(f"(keeping {describe(large)}): skew")
    assert camera.offer(None, "skew") is None and camera.intrinsics == large  # WARN once per problem
    assert camera.problems() == ["camera_info refused"]
    assert intrinsics_mismatch(small, small) is None
    nudged = replace(small, fx=small.fx + 0.5)
    assert intrinsics_mismatch(nudged, small) == f"fx {nudged.fx:.3f} != {small.fx:.3f}"


def test_server_stats_are_computed_once_for_diagnostics_and_the_summary():
    stats = ServerStats(slot_s=0.1, history=3)
    for latency, source in ((50.0, "image"), (150.0, "fallback"), (20.0, "render"), (30.0, "render")):
        stats.record(latency, source, {"render": latency / 2, "total": latency})
    summary = stats.summary({UplinkFault.LATE: 2})
    assert summary["slots"] == 4 and summary["slots_on_time"] == 3
    assert summary["sources"] == {"image": 1, "fallback": 1, "render": 2} and summary["faults"] == {"late": 2}
    assert summary["latency_ms_p50"] == 30.0 and summary["compose_ms_p50"] == {"render": 15.0, "total": 30.0}
    assert summary["latency_ms_p99"] == pytest.approx(147.6)  # over the last 3 slots: 20, 30, 150
    assert json.loads(json.dumps(summary)) == summary
    camera = RenderIntrinsics()
    values, problems = diagnostic_report(summary, camera)
    assert values["latency_ms_p99"] == 147.6 and json.loads(values["sources"]) == summary["sources"]
    assert values["camera_info"] == WAITING and problems == ["uplink faults counted", WAITING]
    camera.offer(Intrinsics.from_fov(32, 24, 1.2))
    assert diagnostic_report(stats.summary({}), camera)[1] == []
    assert ServerStats(0.1).summary({})["latency_ms_p50"] == 0.0  # nothing composed yet


@pytest.fixture
def server_node(tmp_path):
    """A ServerNode on a small point model, recording to ``tmp_path/rec``, in its own context and domain."""
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env()["ROS_DOMAIN_ID"]))
    try:
        node = ServerNode(context=ctx, parameter_overrides=[
            Parameter("model_path", value=str(make_point_model(tmp_path, n=50))),
            Parameter("record_dir", value=str(tmp_path / "rec")),
            Parameter("live_parameter_changes", value=True)])  # issue 28: live changes are off unless started on
        yield node
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


@pytest.mark.ros
def test_server_node_wires_the_slot_core_and_its_policies(server_node, tmp_path):
    """The thin node: no simulation parameter; the slot clock waits for camera_info; each slot's mr/image (in
    the camera's optical frame) is followed by its mr/slot_info; a new calibration sizes the next image, an
    unusable one is refused; live parameters; /diagnostics and server_summary.json from one set of stats."""
    node = server_node
    for gone in ("evaluate_ground_truth", "hindsight_jpeg_quality", "ground_truth_dir"):
        assert not node.has_parameter(gone)
    published: list[tuple[str, object]] = []
    for pub, topic in ((node._pub_mr, "mr/image"), (node._pub_info, "mr/slot_info"), (node._pub_diag, "diag")):
        pub.publish = lambda msg, topic=topic: published.append((topic, msg))
    slot_ns = node.clock.slot_len_ns
    now = {"ns": 1_000_000 * slot_ns}
    node.get_clock = lambda: SimpleNamespace(now=lambda: SimpleNamespace(nanoseconds=now["ns"]))
    node._tick()
    assert node.cursor.next is None  # no camera_info yet: the slot clock waits
    small, large = Intrinsics.from_fov(32, 24, 1.2), Intrinsics.from_fov(48, 36, 1.0)
    node.use_camera_info(camera_info_from_intrinsics(small, 0, CAMERA_OPTICAL_FRAME))
    assert node.camera.intrinsics == small == node.composer.intrinsics
    node._tick()  # the clock starts at the next slot
    first = node.cursor.next
    node._on_ledger(ledger_to_msg(_ledger(first, 0)))
    node.uplink.on_key(PoseKey(first, 0.5, 0.0, 0.1), first, now["ns"])
    now["ns"] = node.clock.start_ns(first) + 1_000_000
    node._tick()  # key + the robot's "no image": complete before its deadline
    assert [t for t, _ in published] == ["mr/image", "mr/slot_info"]
    image, info = published[0][1], mr_slot_info_from_msg(published[1][1])
    assert (image.width, image.height, image.header.frame_id) == (32, 24, CAMERA_OPTICAL_FRAME)
    assert info == MRSlotInfo(first, RealSource.RENDER, 0.5, 0.0, 0.1, 0.0)
    distorted = camera_info_from_intrinsics(large, 0, CAMERA_OPTICAL_FRAME)
    distorted.d = [0.1, 0.0, 0.0, 0.0, 0.0]
    node.use_camera_info(camera_info_from_intrinsics(large, 0, CAMERA_OPTICAL_FRAME))
    node.use_camera_info(distorted)
    assert node.camera.intrinsics == large and node.camera.status.startswith("unusable:")
    now["ns"] += 45 * slot_ns  # 4.5 s stall: past max_backlog_slots, one skip ahead
    node._tick()
    assert node.uplink.faults[UplinkFault.SKIPPED_SLOTS] == 1
    assert published[-2][0] == "mr/image" and (published[-2][1].width, published[-2][1].height) == (48, 36)
    assert mr_slot_info_from_msg(published[-1][1]).source == RealSource.FALLBACK  # the key's pose, extrapolated
    # live parameters act, read-only and out-of-range ones are refused
    assert node.set_parameters([Parameter("jpeg_quality", value=70)])[0].successful
    assert node.params.jpeg_quality == node.core.jpeg_quality == 70
    assert not node.set_parameters([Parameter("max_backlog_slots", value=0)])[0].successful
    read_only = node.set_parameters([Parameter("render_threads", value=2)])[0]
    assert not read_only.successful and "read-only" in read_only.reason
    del node.get_clock  # the node's own clock again (diagnostics are stamped with it)
    node._publish_diagnostics()
    status = published[-1][1].status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert values["slots"] == "2" and json.loads(values["faults"]) == {"skipped_slots": 1, "missing_key": 1}
    assert "camera_info refused" in status.message and "uplink faults counted" in status.message
    node.on_shutdown()
    summary = json.loads((tmp_path / "rec" / "server_summary.json").read_text())
    # the stats and, since issue 28, what the known-writer and plausibility checks refused and the live changes
    assert summary == json.loads(json.dumps({**node.stats.summary(node.uplink.faults), **node.security_summary()}))
    assert summary["parameter_changes"] == {"jpeg_quality": 1} and summary["writers_refused"] == {}
    assert summary["slots"] == 2 and summary["sources"] == {"render": 1, "fallback": 1}


@pytest.mark.ros
def test_server_node_records_the_images_it_received_with_their_keys(server_node, tmp_path):
    """Issue 27's training data: a slot composed with the robot's image records that JPEG byte for byte and its pose
    key (a PoseStamped of base_link in map; both stamped at the slot start); a key-only slot and a slot whose image
    did not decode record neither. ``gsrmr-dataset`` turns the run into a dataset: one frame per received image, its
    camera where the key and the camera mount put it."""
    from gsrmr_common.camera import camera_from_pose
    from gsrmr_common.jpeg import encode_jpeg
    from gsrmr_common.nerfstudio import read_dataset
    from gsrmr_offline.bag_dataset import BagDatasetOptions, build_dataset
    from gsrmr_offline.bag_poses import read_camera_mount
    from gsrmr_server.recording import TOPIC_CAMERA_INFO, TOPIC_RECEIVED_IMAGE, TOPIC_RECEIVED_POSE, read_mcap

    node = server_node
    node._pub_mr.publish = node._pub_info.publish = node._pub_mr_c.publish = lambda _msg: None
    now = {"ns": 1_000_000 * node.clock.slot_len_ns}
    node.get_clock = lambda: SimpleNamespace(now=lambda: SimpleNamespace(nanoseconds=now["ns"]))
    k = Intrinsics.from_fov(32, 24, 1.2)
    node.use_camera_info(camera_info_from_intrinsics(k, 0, CAMERA_OPTICAL_FRAME))
    node._tick()
    first = node.cursor.next
    rng = np.random.default_rng(0)
    jpegs = [encode_jpeg(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8), 90) for _ in range(2)]
    uploads = {first: (1, jpegs[0]), first + 1: (0, None), first + 2: (1, b"\xff\xd8 not a jpeg"),
               first + 3: (1, jpegs[1])}
    keys = {slot: PoseKey(slot, 0.5 + 0.3 * (slot - first), -1.0, 0.25 + 0.2 * (slot - first)) for slot in uploads}
    for slot, (x, data) in uploads.items():
        node._on_ledger(ledger_to_msg(_ledger(slot, x)))
        node.uplink.on_key(keys[slot], slot, now["ns"])
        if data is not None:
            node.uplink.on_image(slot, data, slot, now["ns"])
        now["ns"] = node.clock.start_ns(slot) + 1_000_000
        node._tick()
    node.on_shutdown()
    run = tmp_path / "rec" / "run.mcap"
    got = [(topic, msg) for topic, _, msg in read_mcap(run) if topic in (TOPIC_RECEIVED_IMAGE, TOPIC_RECEIVED_POSE)]
    assert [topic for topic, _ in got] == [TOPIC_RECEIVED_IMAGE, TOPIC_RECEIVED_POSE] * 2
    for (_, image), (_, pose), slot, jpeg in zip(got[::2], got[1::2], (first, first + 3), jpegs, strict=True):
        stamp_ns = node.clock.start_ns(slot)
        assert bytes(image.data) == jpeg and image.format == "rgb8; jpeg compressed bgr8"  # image_transport's
        assert image.header.frame_id == CAMERA_OPTICAL_FRAME and pose.header.frame_id == "map"
        for msg in (image, pose):
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp_ns
        position, q = pose.pose.position, pose.pose.orientation
        assert (position.x, position.y, position.z) == (keys[slot].a_m, keys[slot].b_m, 0.0)
        assert 2 * math.atan2(q.z, q.w) == pytest.approx(keys[slot].theta_rad) and q.x == q.y == 0.0
    # the run as a dataset, as an operator would make it (every received frame kept: no blur or spacing rule)
    mount_file = Path(__file__).resolve().parents[2] / "config" / "camera_mount.yaml"
    build_dataset(BagDatasetOptions(run, tmp_path / "ds", image_topic=TOPIC_RECEIVED_IMAGE,
                                    camera_info_topic=TOPIC_CAMERA_INFO, pose_topic=TOPIC_RECEIVED_POSE,
                                    camera_mount_file=mount_file, blur_ratio=0.0, min_translation_m=0.0,
                                    min_rotation_deg=0.0))
    frames = read_dataset(tmp_path / "ds")
    assert len(frames) == 2
    mount = read_camera_mount(mount_file)
    for frame, slot in zip(frames, (first, first + 3), strict=True):
        want = camera_from_pose(keys[slot].a_m, keys[slot].b_m, keys[slot].theta_rad, mount, k)
        assert np.allclose(frame.camera.camera_to_world, want.camera_to_world, atol=1e-6)
        assert frame.pose == pytest.approx((keys[slot].a_m, keys[slot].b_m, keys[slot].theta_rad))


@pytest.mark.ros
def test_a_new_model_path_is_swapped_in_at_a_slot_boundary_without_missing_a_slot(server_node, tmp_path):
    """Issue 27's hot swap: ``model_path`` set at run time (a live change) is loaded off the slot path; the slots
    composed meanwhile keep the old model, the first slot after the load uses the new one, none is skipped; a path
    that is no file is refused; /diagnostics names the model in use."""
    node = server_node
    published = []
    node._pub_mr.publish = lambda msg: published.append(msg)
    node._pub_info.publish = node._pub_mr_c.publish = lambda _msg: None
    now = {"ns": 1_000_000 * node.clock.slot_len_ns}
    node.get_clock = lambda: SimpleNamespace(now=lambda: SimpleNamespace(nanoseconds=now["ns"]))
    node.use_camera_info(camera_info_from_intrinsics(Intrinsics.from_fov(32, 24, 1.2), 0, CAMERA_OPTICAL_FRAME))
    node._tick()
    first = node.cursor.next
    old = node.composer.model
    refused = node.set_parameters([Parameter("model_path", value=str(tmp_path / "missing.ply"))])[0]
    assert not refused.successful and "is no file" in refused.reason
    new_path = make_point_model(tmp_path / "v1", n=80)
    loaded = threading.Event()  # the load waits for the test: three slots are composed while it "runs"
    load = node.model_swap._load
    node.model_swap._load = lambda path: (loaded.wait(10.0), load(path))[1]
    assert node.set_parameters([Parameter("model_path", value=str(new_path))])[0].successful
    used = []
    for slot in range(first, first + 200):  # up to 10 s for the load, a bound against never
        if slot == first + 3:
            loaded.set()
        node.uplink.on_key(PoseKey(slot, 0.5, 0.0, 0.1), slot, now["ns"])
        node._on_ledger(ledger_to_msg(_ledger(slot, 0)))
        now["ns"] = node.clock.start_ns(slot) + 1_000_000
        node._tick()
        used.append(node.composer.model.num_gaussians)
        if used[-1] == 80:
            break
        time.sleep(0.05)  # the loader thread runs meanwhile
    assert used[:3] == [50, 50, 50] and used[-1] == 80 and old.num_gaussians == 50  # the old model until ready
    assert len(published) == len(used)  # one MR image per slot, none skipped while loading
    assert node.uplink.faults[UplinkFault.SKIPPED_SLOTS] == 0 and node.model_swap.swaps == 1
    del node.get_clock
    diag = []
    node._pub_diag.publish = diag.append
    node._publish_diagnostics()
    values = {kv.key: kv.value for kv in diag[-1].status[0].values}
    assert values["model"] == str(new_path) and values["model_gaussians"] == "80" and values["model_swaps"] == "1"
