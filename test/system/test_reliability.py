"""Reliability and security: uplink faults, node crashes, hostile input and serial faults.

Pure part (no ROS): the fault injector of :mod:`gsrmr_sim.fault_relay`, replayed slot by slot
through the server's own :class:`~gsrmr_server.uplink.UplinkAssembler` and
:class:`~gsrmr_server.compose.MRComposer` — every slot composed, every injected fault counted exactly
once under its server name; guarded decoding and file parsing against hostile input.

ROS part (processes over DDS, ``ros`` + ``slow`` markers): robot → relay (all faults on) → server with
the real stack; kill -9 of robot and scheduler mid-run; hostile messages at the server; the mock LIMO
with serial faults under the LIMO driver node.
"""

from __future__ import annotations

from collections import Counter
import math
import pickle

import numpy as np
import pytest

from gsrmr_common.jpeg import ImageRejected, decode_jpeg, encode_jpeg, jpeg_header
from gsrmr_common.wire import PoseKey
from gsrmr_sim.fault_relay import (
    ALL_FAULTS,
    IMAGE_FAULTS,
    KEY_FAULTS,
    FaultInjector,
    FaultRates,
    Upload,
    corrupt_jpeg,
    forge_jpeg_header,
    resize_jpeg,
    truncate_jpeg,
)

W, H = 80, 60
SLOT_NS = 100_000_000


def _image(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W]
    base = np.stack([xx * 3 % 256, yy * 4 % 256, (xx + yy) * 2 % 256], axis=2)
    return np.clip(base + rng.integers(0, 20, (H, W, 3)), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def jpeg() -> bytes:
    return encode_jpeg(_image(), 80)


@pytest.fixture(scope="module")
def composer():
    from gsrmr_server.compose import MRComposer
    from gsrmr_sim.world.recorder import with_resolution
    from gsrmr_sim.world.scene import load_scene
    from gsrmr_sim.world.virtual import virtual_view
    from gsrmr_splat.model import GaussianModel

    scene = with_resolution(load_scene("sandbox"), W, H)
    rng = np.random.default_rng(3)
    model = GaussianModel.from_points(rng.uniform([-3, -3, 0], [3, 3, 1.5], (500, 3)),
                                      rng.uniform(0, 1, (500, 3)), scales_m=0.05, opacities=0.5)
    return MRComposer(model, virtual_view(scene), scene.camera.intrinsics, scene.camera.mount,
                      scene.background)


# ------------------------------------------------------------------------------------ mutators

def test_mutators_produce_the_fault_they_name(jpeg):
    assert decode_jpeg(jpeg, expected_shape=(H, W)).shape == (H, W, 3)
    with pytest.raises(ImageRejected, match=r"truncated|corrupt"):
        decode_jpeg(truncate_jpeg(jpeg))
    rng = np.random.default_rng(0)
    for _ in range(50):  # a flipped bit in any header marker is caught by the structure walk
        with pytest.raises(ImageRejected):
            decode_jpeg(corrupt_jpeg(jpeg, rng))
    small = resize_jpeg(jpeg)
    assert jpeg_header(small).width == W // 2 and jpeg_header(small).height == H // 2
    with pytest.raises(ImageRejected, match="expected"):
        decode_jpeg(small, expected_shape=(H, W))
    forged = forge_jpeg_header(jpeg)
    assert (jpeg_header(forged).width, jpeg_header(forged).height) == (20000, 20000)
    assert len(forged) == len(jpeg)


def test_forged_header_is_refused_before_any_pixel_is_decoded(jpeg, monkeypatch):
    import cv2

    import gsrmr_common.jpeg as jpeg_mod

    def no_decode(*_a, **_k):
        raise AssertionError("imdecode called on a forged header")

    monkeypatch.setattr(jpeg_mod.cv2, "imdecode", no_decode)
    with pytest.raises(ImageRejected, match="20000×20000"):
        decode_jpeg(forge_jpeg_header(jpeg))
    with pytest.raises(ImageRejected, match="exceeds"):  # oversized payload: refused on length alone
        decode_jpeg(b"\xff\xd8" + bytes(9 * 1024 * 1024))
    monkeypatch.undo()
    assert cv2.imdecode is not no_decode


def test_refusal_fault_names_each_refusal(jpeg):
    from gsrmr_server.compose import refusal_fault

    assert refusal_fault(resize_jpeg(jpeg), W, H) == "wrong_size"
    assert refusal_fault(forge_jpeg_header(jpeg), W, H) == "oversized_header"
    assert refusal_fault(truncate_jpeg(jpeg), W, H) == "corrupt_image"
    assert refusal_fault(b"not a jpeg", W, H) == "corrupt_image"


def test_composer_counts_a_wrong_size_upload_as_wrong_size(jpeg, composer):
    from gsrmr_server.uplink import SlotUploads

    key = PoseKey(7, 0.0, 0.0, 0.0)
    out = composer.compose(SlotUploads(7, key=key, jpeg=resize_jpeg(jpeg)), key, 0.0)
    assert out.faults == ["wrong_size"] and out.source == "fallback" and out.mr.shape == (H, W, 3)
    out = composer.compose(SlotUploads(7, key=key, jpeg=forge_jpeg_header(jpeg)), key, 0.0)
    assert out.faults == ["oversized_header"]
    out = composer.compose(SlotUploads(7, key=key, jpeg=jpeg), key, 0.0)
    assert out.faults == [] and out.source == "image"


# ------------------------------------------------------------------------------------ injector

def test_rates_are_validated_with_a_reason():
    with pytest.raises(ValueError, match="drop_rate"):
        FaultRates(drop=1.5)
    with pytest.raises(ValueError, match="drop_rate"):
        FaultRates(drop=math.nan)
    with pytest.raises(ValueError, match="sum to"):
        FaultRates(drop=0.6, duplicate=0.6)
    assert FaultRates().drop == pytest.approx(0.10)
    with pytest.raises(ValueError, match="delay_slots"):
        FaultInjector(FaultRates(), delay_slots=0.5)


def test_zero_rates_relay_is_transparent(jpeg):
    inj = FaultInjector(FaultRates.none(), seed=1)
    for k in range(20):
        up = Upload("image", k * SLOT_NS, jpeg)
        assert inj.push(up, k * SLOT_NS) == [up]
    assert inj.injected == Counter({"image.forwarded": 20})


def test_reorder_swaps_with_successor_and_delay_exceeds_a_slot(jpeg):
    only_reorder = FaultRates(**{**{f: 0.0 for f in ALL_FAULTS}, "reorder": 1.0})
    inj = FaultInjector(only_reorder, seed=0)
    assert inj.push(Upload("key", 0, (0.0, 0.0, 0.0)), 0) == []
    out = inj.push(Upload("key", SLOT_NS, (1.0, 0.0, 0.0)), SLOT_NS)  # one held at a time: passes
    assert [u.stamp_ns for u in out] == [SLOT_NS, 0]
    only_delay = FaultRates(**{**{f: 0.0 for f in ALL_FAULTS}, "delay": 1.0})
    inj = FaultInjector(only_delay, seed=0, delay_slots=1.5)
    assert inj.push(Upload("key", 0, (0.0, 0.0, 0.0)), 0) == []
    assert inj.due(SLOT_NS) == []
    assert [u.fault for u in inj.due(SLOT_NS * 3 // 2)] == ["delay"]


def test_injection_is_reproducible_from_the_seed(jpeg):
    def run(seed):
        inj = FaultInjector(FaultRates(), seed=seed)
        log = []
        for k in range(200):
            for up in inj.push(Upload("key", k * SLOT_NS, (k, 0.0, 0.0)), k * SLOT_NS):
                log.append((up.kind, up.stamp_ns, up.fault))
        return log, dict(inj.injected)

    assert run(5) == run(5)
    assert run(5) != run(6)


def _replay(composer, jpeg: bytes, slots: int, seed: int) -> tuple[FaultInjector, Counter, list]:
    """Robot → injector → server core, slot by slot on a simulated clock.

    Slot k: the robot sends key and image at k·τ + 1 ms; the server composes slot k at k·τ + 30 ms
    (its ``process_delay_s``) with the schedule saying "image" for every slot.
    """
    from gsrmr_server.uplink import UplinkAssembler

    inj = FaultInjector(FaultRates(), seed=seed, slot_s=SLOT_NS / 1e9)
    asm = UplinkAssembler()
    composed = []
    k0 = 10_000
    asm.take(k0 - 1)  # the server has been running: slots before k0 are closed
    asm.faults.clear()

    def deliver(uploads, now_ns):
        now_slot = now_ns // SLOT_NS
        for up in uploads:
            if up.kind == "key":
                asm.on_key(PoseKey((up.stamp_ns + SLOT_NS // 2) // SLOT_NS, *up.data), now_slot, now_ns)
            else:
                asm.on_image((up.stamp_ns + SLOT_NS // 2) // SLOT_NS, up.data, now_slot, now_ns)

    for k in range(k0, k0 + slots):
        t_send = k * SLOT_NS + 1_000_000
        deliver(inj.due(t_send), t_send)
        pose = (0.01 * (k - k0), 0.0, 0.0)
        deliver(inj.push(Upload("key", k * SLOT_NS, pose), t_send), t_send)
        deliver(inj.push(Upload("image", k * SLOT_NS, jpeg), t_send + 500_000), t_send + 500_000)
        t_compose = k * SLOT_NS + 30_000_000
        deliver(inj.due(t_compose), t_compose)
        uploads = asm.take(k, image_expected=True)
        result = composer.compose(uploads, asm.best_pose(k), (k - k0) * 0.1)
        for fault in result.faults:
            if fault not in uploads.faults:
                asm.count(fault)
        composed.append((k, result.source, result.mr.shape))
    end = (k0 + slots + 5) * SLOT_NS
    deliver(inj.due(end), end)  # everything still held arrives after its slot was composed
    assert inj.held() == 0
    return inj, asm.faults, composed


def test_every_injected_fault_reaches_the_server_counters_exactly(composer, jpeg):
    slots = 300
    inj, server, composed = _replay(composer, jpeg, slots, seed=11)
    # Every slot yields an MR image of the right size, in order, none skipped.
    assert [c[0] for c in composed] == list(range(10_000, 10_000 + slots))
    assert all(c[2] == (H, W, 3) for c in composed)
    n = inj.injected
    for kind, names in (("key", KEY_FAULTS), ("image", IMAGE_FAULTS)):
        for name in names:
            assert n[f"{kind}.{name}"] > 0, f"{kind}.{name} never injected in {slots} slots"
    assert server["duplicate_key"] == n["key.duplicate"]
    assert server["duplicate_image"] == n["image.duplicate"]
    assert server["invalid_key"] == n["key.nan_key"]
    late = sum(n[f"{kind}.{f}"] for kind in ("key", "image") for f in ("reorder", "delay", "stale"))
    assert server["late"] == late
    assert server["missing_key"] == sum(n[f"key.{f}"] for f in ("drop", "reorder", "delay", "stale", "nan_key"))
    assert server["missing_image"] == sum(n[f"image.{f}"] for f in ("drop", "reorder", "delay", "stale"))
    assert server["corrupt_image"] == n["image.truncate"] + n["image.corrupt"]
    assert server["wrong_size"] == n["image.wrong_size"]
    assert server["oversized_header"] == n["image.forged_header"]
    sources = Counter(c[1] for c in composed)
    assert sources["image"] + sources["fallback"] + sources["render"] == slots


# ------------------------------------------------------------------------------------ model files

class _Evil:
    def __reduce__(self):
        return (exec, ("import pathlib; pathlib.Path('PWNED').write_text('x')",))


def test_model_files_are_parsed_without_pickle(tmp_path, monkeypatch):
    from gsrmr_splat.model import GaussianModel, PlyFormatError

    monkeypatch.chdir(tmp_path)
    evil = tmp_path / "model.ply"
    evil.write_bytes(pickle.dumps(_Evil()))
    with pytest.raises(PlyFormatError):
        GaussianModel.load_ply(evil)
    assert not (tmp_path / "PWNED").exists()
    header_only = tmp_path / "trunc.ply"
    header_only.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000\nproperty float x\n"
                            b"end_header\n" + bytes(12))
    with pytest.raises(PlyFormatError):
        GaussianModel.load_ply(header_only)
    not_3dgs = tmp_path / "points.ply"
    not_3dgs.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n")
    with pytest.raises(PlyFormatError, match="missing"):
        GaussianModel.load_ply(not_3dgs)


def test_training_checkpoint_load_refuses_arbitrary_pickle(tmp_path, monkeypatch):
    """A checkpoint carrying a pickled callable is refused (torch.load(weights_only=True)); nothing runs."""
    import torch

    from gsrmr_splat.train import Trainer

    monkeypatch.chdir(tmp_path)
    evil = tmp_path / "evil.ckpt"
    torch.save({"params": _Evil()}, evil)
    with pytest.raises(pickle.UnpicklingError):
        Trainer.load_checkpoint(object.__new__(Trainer), evil)  # torch.load runs before any state is touched
    assert not (tmp_path / "PWNED").exists()


# ==================================================================================== over DDS

RELAY_RATES = {"drop": 0.10, "duplicate": 0.05, "reorder": 0.05, "delay": 0.05, "stale": 0.05, "nan_key": 0.05,
               "truncate": 0.05, "corrupt": 0.05, "wrong_size": 0.05, "forged_header": 0.05}
# Each relay fault → the server counter(s) that must show it.
EXPECTED_SERVER_FAULTS = ("missing_key", "missing_image", "duplicate_key", "duplicate_image", "late", "invalid_key",
                          "corrupt_image", "wrong_size", "oversized_header")


def _harness():
    from pathlib import Path
    import sys

    sys.path.insert(0, str(Path(__file__).parents[1]))
    from support import stack_harness

    return stack_harness


@pytest.fixture(scope="module")
def relay_stack(tmp_path_factory):
    """robot → /robot/uplink/* → relay (every fault on, seed 0) → uplink/* → server; scheduler plans all images."""
    from conftest import ros_env

    from gsrmr_sim.sim_stack import ProcessSpec, config_dir

    h = _harness()
    tmp = tmp_path_factory.mktemp("relay_stack")
    model = h.make_point_model(tmp)
    remap = [("uplink/pose_key", "/robot/uplink/pose_key"),
             ("uplink/image_raw/compressed", "/robot/uplink/image_raw/compressed")]
    relay = ProcessSpec("gsrmr-uplink-relay", "gsrmr_uplink_relay", [str(config_dir() / "link.yaml")],
                        {"input_prefix": "/robot", "seed": 0, "summary_path": str(tmp / "relay_summary.json"),
                         **{f"{k}_rate": v for k, v in RELAY_RATES.items()}})
    # issue 28: the relay writes the server's and the scheduler's uplink, and is the robot's image reader; this
    # module's test client ("test_reliability") lies to the server with malformed uploads: listed, so that the
    # checks behind the writer check (malformed, oversized) are what it meets
    relayed = ["gsrmr_robot", "gsrmr_uplink_relay"]
    s = h.Stack(tmp, model, ros_env(), remappings={"gsrmr_robot": remap}, extra=(relay,),
                overrides={"gsrmr_scheduler": {"loss_threshold": 0.0, "horizon": 400, "replan_period_s": 1.0,
                                               "robot_writers": relayed},
                           "gsrmr_server": {"robot_writers": [*relayed, "test_reliability"]},
                           "gsrmr_robot": {"image_readers": ["gsrmr_uplink_relay"]}})
    s.start_all()
    try:
        yield s
    finally:
        s.stop()


@pytest.fixture(scope="module")
def relay_client(relay_stack):
    from diagnostic_msgs.msg import DiagnosticArray

    with _harness().ros_client(relay_stack.env, "test_reliability") as (node, ex):
        latest: dict[str, dict[str, str]] = {}

        def on_diag(msg: DiagnosticArray) -> None:
            for st in msg.status:
                latest[st.name.split(":")[0]] = {kv.key: kv.value for kv in st.values}

        node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 50)
        yield node, ex, latest


def _server_faults(latest) -> Counter:
    import json

    return Counter(json.loads(latest.get("gsrmr_server", {}).get("faults", "{}")))


def _consecutive(rows) -> bool:
    slots = [int(r["slot"]) for r in rows]
    return slots == list(range(slots[0], slots[0] + len(slots)))


@pytest.mark.ros
@pytest.mark.slow
def test_uplink_faults_through_relay_every_slot_composed_every_fault_counted(relay_stack, relay_client):
    h = _harness()
    _node, ex, latest = relay_client
    # Server up first (it loads for seconds; keys sent before reach only the scheduler): then a server
    # snapshot S1 and a relay snapshot R1 taken after it — every fault the relay counts after R1 was
    # sent after S1, so the server's count grows by at least as much.
    assert h.spin_until(ex, lambda: "gsrmr_server" in latest, 60), relay_stack.log("gsrmr_server")[-2000:]
    server1 = _server_faults(latest)
    latest.pop("gsrmr_uplink_relay", None)
    assert h.spin_until(ex, lambda: "gsrmr_uplink_relay" in latest, 10)
    relay1 = Counter({k: int(v) for k, v in latest["gsrmr_uplink_relay"].items() if k.startswith(("key.", "image."))})

    def relay_injected_all() -> bool:
        r = latest.get("gsrmr_uplink_relay", {})  # each fault injected at least once after R1
        return all(int(r.get(f"key.{f}", 0)) > relay1[f"key.{f}"] for f in KEY_FAULTS) and \
            all(int(r.get(f"image.{f}", 0)) > relay1[f"image.{f}"] for f in IMAGE_FAULTS)

    assert h.spin_until(ex, relay_injected_all, 90), (latest.get("gsrmr_uplink_relay"),
                                                      relay_stack.log("gsrmr_uplink_relay")[-2000:])
    relay = Counter({k: int(v) for k, v in latest["gsrmr_uplink_relay"].items() if k.startswith(("key.", "image."))})
    assert h.spin_until(ex, lambda: all(_server_faults(latest)[f] > 0 for f in EXPECTED_SERVER_FAULTS), 30), \
        (_server_faults(latest), relay)
    h.spin_until(ex, lambda: False, 2.5)  # a server diagnostic published after the relay's snapshot
    server = _server_faults(latest)
    new_server, new_relay = server - server1, relay - relay1
    assert new_relay["key.nan_key"] > 0
    assert new_server["invalid_key"] >= new_relay["key.nan_key"], (server, relay)  # refused on arrival
    for name, proc in relay_stack.procs.items():
        assert proc.poll() is None, (name, relay_stack.log(name)[-2000:])
    rows = h.slot_rows(relay_stack.tmp / "rec")
    assert len(rows) > 30 and _consecutive(rows), [r["slot"] for r in rows][:20]
    sources = [r["source"] for r in rows]
    assert set(sources) <= {"image", "render", "fallback", "none"}
    assert {"image", "fallback"} <= set(sources)
    # "none" (no pose key received yet: the background) only before the first key of the run
    first_keyed = next(i for i, s in enumerate(sources) if s != "none")
    assert "none" not in sources[first_keyed:], sources
    # Refusals found while composing are in the per-slot log too.
    logged = Counter(f for r in rows for f in (r["faults"] or "").split(";") if f)
    for fault in ("corrupt_image", "wrong_size", "oversized_header", "missing_key"):
        assert logged[fault] > 0, logged


@pytest.mark.ros
@pytest.mark.slow
def test_kill9_robot_and_scheduler_others_carry_on_scheduler_resumes(relay_stack, relay_client):
    import json
    import re
    import time

    h = _harness()
    _node, ex, _latest = relay_client
    rec, state = relay_stack.tmp / "rec", relay_stack.tmp / "sched_state" / "schedule.json"
    assert h.spin_until(ex, state.exists, 30), relay_stack.log("gsrmr_scheduler")[-2000:]
    relay_stack.kill9("gsrmr_scheduler")
    saved_seq = int(json.loads(state.read_text())["data"][2])
    rows_before = h.slot_rows(rec)
    relay_stack.kill9("gsrmr_robot")
    h.spin_until(ex, lambda: False, 1.5)
    for name, proc in relay_stack.procs.items():
        if name not in ("gsrmr_robot", "gsrmr_scheduler"):
            assert proc.poll() is None, (name, relay_stack.log(name)[-2000:])
    rows = h.slot_rows(rec)
    assert rows[:len(rows_before)] == rows_before  # nothing the recorder wrote was lost
    assert len(rows) > len(rows_before)  # and the server kept composing without robot and scheduler
    assert _consecutive(rows)
    restart_slot = int(rows[-1]["slot"])
    t0 = time.monotonic()
    relay_stack.start("gsrmr_scheduler")
    relay_stack.start("gsrmr_robot")
    assert h.spin_until(ex, lambda: "resumed schedule seq" in relay_stack.log("gsrmr_scheduler"), 60), \
        relay_stack.log("gsrmr_scheduler")[-2000:]
    resumed = int(re.findall(r"resumed schedule seq (\d+)", relay_stack.log("gsrmr_scheduler"))[-1])
    assert resumed == saved_seq, (resumed, saved_seq, time.monotonic() - t0)
    # The restarted robot uploads again: image slots after the restart.
    assert h.spin_until(ex, lambda: any(int(r["slot"]) > restart_slot and r["source"] == "image"
                                        for r in h.slot_rows(rec)), 60), relay_stack.log("gsrmr_robot")[-2000:]
    assert _consecutive(h.slot_rows(rec))


@pytest.mark.ros
@pytest.mark.slow
def test_kill9_relay_camera_and_base_others_carry_on(relay_stack, relay_client):
    h = _harness()
    _node, ex, _latest = relay_client
    rec = relay_stack.tmp / "rec"
    victims = ("gsrmr_uplink_relay", "gsrmr_mock_camera", "gsrmr_limo_base")
    rows_before = h.slot_rows(rec)
    for name in victims:
        relay_stack.kill9(name)
    h.spin_until(ex, lambda: False, 1.5)
    for name, proc in relay_stack.procs.items():
        if name not in victims:
            assert proc.poll() is None, (name, relay_stack.log(name)[-2000:])
    rows = h.slot_rows(rec)
    assert rows[:len(rows_before)] == rows_before and len(rows) > len(rows_before) and _consecutive(rows)
    restart_slot = int(rows[-1]["slot"])
    for name in victims:
        relay_stack.start(name)
    assert h.spin_until(ex, lambda: any(int(r["slot"]) > restart_slot and r["source"] == "image"
                                        for r in h.slot_rows(rec)), 60), relay_stack.log("gsrmr_uplink_relay")[-2000:]
    assert _consecutive(h.slot_rows(rec))


def _set_params(node, ex, target: str, params: dict) -> list:
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    h = _harness()
    cli = node.create_client(SetParameters, f"{target}/set_parameters")
    assert cli.wait_for_service(timeout_sec=15)
    request = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in params.items()])
    return h.call_service(ex, cli, request, timeout_s=30).results


@pytest.mark.ros
@pytest.mark.slow
def test_hostile_messages_and_parameters_at_the_server(relay_stack, relay_client):
    from geometry_msgs.msg import Vector3Stamped
    from nav_msgs.msg import Odometry
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import CompressedImage, Image
    from std_msgs.msg import Float64MultiArray

    from gsrmr_common.ros_wire import compressed_to_msg, image_to_msg, ns_to_stamp
    from gsrmr_common.wire import LEDGER_FIELDS

    h = _harness()
    node, ex, latest = relay_client
    # Out-of-range parameters are refused with a reason (relay, server).
    res = _set_params(node, ex, "gsrmr_uplink_relay", {"drop_rate": 2.0})
    assert not res[0].successful and res[0].reason
    for k in RELAY_RATES:  # turn the relay transparent, so the counters below are the test's alone
        assert _set_params(node, ex, "gsrmr_uplink_relay", {f"{k}_rate": 0.0})[0].successful
    res = _set_params(node, ex, "gsrmr_uplink_relay", {"drop_rate": 0.6})
    assert res[0].successful
    res = _set_params(node, ex, "gsrmr_uplink_relay", {"duplicate_rate": 0.6})
    assert not res[0].successful and "sum to" in res[0].reason, res[0].reason
    assert _set_params(node, ex, "gsrmr_uplink_relay", {"drop_rate": 0.0})[0].successful
    res = _set_params(node, ex, "gsrmr_server", {"process_delay_s": -1.0})
    assert not res[0].successful and res[0].reason
    res = _set_params(node, ex, "gsrmr_server", {"jpeg_quality": 1000})
    assert not res[0].successful and res[0].reason
    h.spin_until(ex, lambda: False, 2.5)  # held messages flushed, a fresh server diagnostic
    before = _server_faults(latest)

    img_pub = node.create_publisher(CompressedImage, "uplink/image_raw/compressed", 10)
    key_pub = node.create_publisher(Vector3Stamped, "uplink/pose_key", 10)
    h.spin_until(ex, lambda: False, 1.0)  # discovery
    now_ns = node.get_clock().now().nanoseconds
    slot_ns = 100_000_000
    future = (now_ns // slot_ns + 10) * slot_ns  # 1 s ahead: the forged image is first for that slot
    real = encode_jpeg(np.zeros((120, 160, 3), np.uint8), 80)
    img_pub.publish(compressed_to_msg(forge_jpeg_header(real), future, "camera_optical_frame"))
    img_pub.publish(compressed_to_msg(b"\xff\xd8" + bytes(9 * 1024 * 1024), future, "camera_optical_frame"))
    bad_stamp = compressed_to_msg(real, future, "camera_optical_frame")
    bad_stamp.header.stamp.nanosec = 2_000_000_000
    img_pub.publish(bad_stamp)
    key = Vector3Stamped()
    key.header.stamp, key.header.frame_id = ns_to_stamp(future), "odom"
    key_pub.publish(key)
    ledger_pub = node.create_publisher(Float64MultiArray, "gsrmr/ledger", 10)
    h.spin_until(ex, lambda: ledger_pub.get_subscription_count() > 0, 5)
    ledger_pub.publish(Float64MultiArray(data=[math.nan] * len(LEDGER_FIELDS)))  # int(NaN) raised before
    # A camera frame and an odometry message with an invalid stamp, at the robot (and the server's evaluator).
    cam_pub = node.create_publisher(Image, "camera/image_raw", qos_profile_sensor_data)
    odom_pub = node.create_publisher(Odometry, "odom", 10)
    h.spin_until(ex, lambda: cam_pub.get_subscription_count() > 0 and odom_pub.get_subscription_count() > 0, 5)
    frame = image_to_msg(np.zeros((120, 160, 3), np.uint8), now_ns, "camera_optical_frame")
    frame.header.stamp.nanosec = 2_000_000_000
    odom = Odometry()
    odom.header.stamp.nanosec = 2_000_000_000
    odom.pose.pose.orientation.w = 1.0
    for _ in range(3):
        cam_pub.publish(frame)
        odom_pub.publish(odom)

    def counted() -> bool:
        d = _server_faults(latest) - before
        return all(d[f] >= 1 for f in ("oversized_header", "oversized_image", "malformed_image", "malformed_key",
                                       "malformed_ledger"))

    assert h.spin_until(ex, counted, 20), (_server_faults(latest) - before)
    h.spin_until(ex, lambda: False, 1.0)
    for name in ("gsrmr_server", "gsrmr_scheduler", "gsrmr_uplink_relay", "gsrmr_robot"):
        assert relay_stack.procs[name].poll() is None, (name, relay_stack.log(name)[-3000:])
    assert _consecutive(h.slot_rows(relay_stack.tmp / "rec"))


@pytest.mark.ros
@pytest.mark.slow
def test_relay_stack_exits_cleanly_with_summaries(relay_stack):
    import json

    took = relay_stack.stop()
    for name, proc in relay_stack.procs.items():
        assert proc.returncode == 0, (name, proc.returncode, relay_stack.log(name)[-1500:])
        assert took[name] < 15, name
    summary = json.loads((relay_stack.tmp / "rec" / "server_summary.json").read_text())
    for fault in EXPECTED_SERVER_FAULTS:
        assert summary["faults"].get(fault, 0) > 0, summary["faults"]
    relay = json.loads((relay_stack.tmp / "relay_summary.json").read_text())
    assert relay["injected"]["key.forwarded"] > 0
    assert "relay summary" in relay_stack.log("gsrmr_uplink_relay")


# ------------------------------------------------------------------------------------ serial faults

def _finite_odom(msg) -> bool:
    p, q, t = msg.pose.pose.position, msg.pose.pose.orientation, msg.twist.twist
    vals = [p.x, p.y, p.z, q.x, q.y, q.z, q.w, t.linear.x, t.linear.y, t.angular.z,
            *msg.pose.covariance, *msg.twist.covariance]
    return all(math.isfinite(v) for v in vals)


@pytest.mark.ros
@pytest.mark.slow
def test_serial_faults_garbage_bitflips_silence_port_loss_during_motion(ros_processes, tmp_path):
    """Mock LIMO with every serial fault on under gsrmr-limo-base: odometry stays finite, the driver
    resyncs and reconnects, the base stops when its commands stop (port loss, then cmd_vel ends)."""
    import time

    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry

    h = _harness()
    link = str(tmp_path / "limo")
    mock = ros_processes.start("gsrmr-mock-limo", "--link", link, "--cmd-timeout-s", "0.3", "--seed", "4",
                               "--garbage-rate", "0.05", "--bit-flip-rate", "0.05", "--silence-every-s", "2.0",
                               "--silence-s", "0.4", "--reopen-every-s", "3.0", "--reopen-gap-s", "0.6")
    ros_processes.wait_for(mock, "mock LIMO ready", timeout_s=20)
    base = ros_processes.start("gsrmr-limo-base", "--ros-args", "-p", f"port:={link}", "-p",
                               "diagnostics_period_s:=0.2", "-p", "cmd_timeout_s:=0.5")
    with h.ros_client(ros_processes.env, "test_serial_faults") as (node, ex):
        odom: list = []
        truth: list[tuple[float, float]] = []  # (monotonic s, true forward speed m/s)
        diag: dict[str, str] = {}
        link_states: set[str] = set()

        def on_diag(msg: DiagnosticArray) -> None:
            for st in msg.status:
                if st.name.startswith("gsrmr_limo_base"):
                    diag.update({kv.key: kv.value for kv in st.values})
                    link_states.add(diag.get("link_connected", ""))

        node.create_subscription(Odometry, "odom", odom.append, 50)
        node.create_subscription(Odometry, "/sim/ground_truth/odom",
                                 lambda m: truth.append((time.monotonic(), m.twist.twist.linear.x)), 50)
        node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 50)
        pub = node.create_publisher(Twist, "cmd_vel", 10)
        cmd = Twist()
        cmd.linear.x, cmd.angular.z = 0.3, 0.2

        def drive(seconds: float, command: Twist | None, until=None) -> None:
            end, next_pub = time.monotonic() + seconds, 0.0
            while time.monotonic() < end and not (until and until()):
                if command is not None and time.monotonic() >= next_pub:
                    pub.publish(command)
                    next_pub = time.monotonic() + 0.05
                ex.spin_once(timeout_sec=0.01)

        assert h.spin_until(ex, lambda: bool(odom) and pub.get_subscription_count() > 0, 30), \
            ros_processes.output(base)
        t_start = time.monotonic()
        drive(20.0, cmd, until=lambda: int(diag.get("connects", "0")) >= 3 and time.monotonic() - t_start > 7)
        moving = [v for t, v in truth if t > t_start + 0.5]
        assert max(moving) > 0.2, "the base never moved"
        assert min(moving) < 0.02, "port loss during motion: the base must stop (watchdog)"
        assert moving[-1] > 0.2 or max(v for t, v in truth if t > time.monotonic() - 2.5) > 0.2, \
            "driving did not resume after the reconnect"
        hostile = Twist()
        hostile.linear.x, hostile.angular.z = math.nan, math.inf
        drive(0.5, hostile)  # a NaN/inf command must not reach the odometry
        drive(0.5, cmd)
        drive(2.0, None)  # cmd_vel stops: the driver's watchdog (0.5 s) stops the base
        assert abs(truth[-1][1]) < 0.02 and abs(odom[-1].twist.twist.linear.x) < 0.05
        assert all(_finite_odom(m) for m in odom), "NaN/inf in odometry"
        assert len(odom) > 100
        assert int(diag["connects"]) >= 3 and int(diag["disconnects"]) >= 2  # reconnected
        assert "False" in link_states  # the port loss was reported
        assert int(diag["parser_skipped_bytes"]) > 0 and int(diag["parser_bad_checksum"]) > 0  # resynced
        assert base.poll() is None
    assert ros_processes.interrupt(base) < 10.0 and base.returncode == 0
    assert ros_processes.interrupt(mock) < 10.0 and mock.returncode == 0
