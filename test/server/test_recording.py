"""Run recorder (gsrmr_server.recording): CSV + MCAP output, ROS 2 compatibility, crash safety."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
import signal
import subprocess
import sys
import textwrap
import time

from geometry_msgs.msg import TwistStamped, Vector3Stamped
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
import numpy as np
import pytest
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import Float64MultiArray, String

from gsrmr_common import ros_wire, wire
from gsrmr_common.jpeg import decode_jpeg
from gsrmr_common.slot_clock import SlotClock
from gsrmr_server import recording as rec
from gsrmr_server.recording import CSV_COLUMNS, RunRecorder, read_mcap, read_slots_csv, recover_run

CLOCK = SlotClock(0.1)
SLOT_NS = CLOCK.slot_len_ns
T0_SLOT = 17_638_000_000  # an epoch-like absolute slot index (2025-11-22 in ROS time at τ = 0.1 s)


def make_row(k: int) -> dict:
    """A fully populated slot row for absolute slot T0_SLOT + k."""
    slot = T0_SLOT + k
    return {"slot": slot, "stamp_s": CLOCK.start_ns(slot) / 1e9, "x": k % 2,
            "power_w": 0.05 + 0.01 * k, "bytes_sent": 24 if k % 2 == 0 else 15_000 + k,
            "energy_j": 1e-3 * (k + 1), "loss": 0.1 / (k + 1), "psnr_db": 20.0 + k, "ssim": 0.9,
            "source": ("render", "image", "fallback")[k % 3], "pose_a_m": 0.1 * k, "pose_b_m": -0.2 * k,
            "pose_theta_rad": math.pi / 7 * k, "latency_ms": 12.5, "faults": "" if k % 4 else "late;retry",
            "gs_loss": 0.02 * k if k % 2 else None, "energy_upload_all_j": 0.5 + k, "channel_gain": 1e-6 * (k + 1),
            "energy_image_j": 0.4 + k, "energy_key_j": 1e-3 * k, "gs_truth_loss": 0.03, "image_truth_loss": 0.01,
            "scored": k % 2, "round_slot": k - 1, "held_back": k % 2, "uplink_rate_bps": 1e6 + k,
            "scene_change": int(k == 1), "frame_stamp_s": CLOCK.start_ns(slot) / 1e9 - 0.03, "correction_seq": k // 3,
            "level": k % 3, "time_left_ms": 70.0 - k, "predicted_ms": 20.5 + k, "compose_ms": 21.25 + k}


def make_image(k: int) -> np.ndarray:
    img = np.zeros((24, 32, 3), np.uint8)
    img[:, : 2 + k % 30] = (220, 30, 20)
    return img


@pytest.mark.parametrize("type_name", sorted(set(rec.TOPIC_TYPES.values())))
def test_message_definition_matches_ros_classes(type_name: str) -> None:
    text = rec.message_definition(type_name)
    top = text.split("=" * 80)[0]
    cls = {"sensor_msgs/msg/CompressedImage": CompressedImage, "geometry_msgs/msg/TwistStamped": TwistStamped,
           "std_msgs/msg/String": String}[type_name]
    names = [line.split()[1] for line in top.splitlines() if line.strip()]
    assert names == list(cls.get_fields_and_field_types())
    if "Header" in text:
        assert "\nMSG: std_msgs/msg/Header\n" in text and "\nMSG: builtin_interfaces/msg/Time\n" in text
    assert "#" not in text


def test_message_definition_unknown_type() -> None:
    with pytest.raises(FileNotFoundError):
        rec.message_definition("sensor_msgs/msg/NoSuchThing")
    with pytest.raises(ValueError):
        rec.message_definition("Image")


def test_round_trip_csv_and_mcap(tmp_path: Path) -> None:
    rows = [make_row(k) for k in range(12)]
    with RunRecorder(tmp_path, segment_slots=5) as recorder:
        for k, row in enumerate(rows):
            image = make_image(k) if k != 3 else None
            cmd = (0.1 * k, -0.05 * k) if k != 4 else None
            recorder.write_slot(row, image, cmd)
            if k == 11:  # two segments are finished and renamed, the third is being written
                names = sorted(p.name for p in tmp_path.iterdir())
                assert names == ["run-0000.mcap", "run-0001.mcap", "run-0002.mcap.part", "slots.csv"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap", "slots.csv"]

    back = read_slots_csv(tmp_path / "slots.csv")
    for row, got in zip(rows, back, strict=True):
        expected = {**row, "faults": row["faults"] or None}
        assert got == expected  # floats survive exactly (repr), empty cells become None

    messages = read_mcap(tmp_path / "run.mcap")
    by_topic: dict[str, list] = {}
    for topic, log_time, msg in messages:
        by_topic.setdefault(topic, []).append((log_time, msg))
    assert len(by_topic[rec.TOPIC_SLOT_LOG]) == 12
    assert len(by_topic[rec.TOPIC_MR_IMAGE]) == 11 and len(by_topic[rec.TOPIC_CMD_VEL]) == 11
    for (log_time, msg), row in zip(by_topic[rec.TOPIC_SLOT_LOG], rows, strict=True):
        assert log_time == CLOCK.start_ns(row["slot"])
        assert json.loads(msg.data)["slot"] == row["slot"]
    image_rows = [r for k, r in enumerate(rows) if k != 3]
    for (log_time, msg), row in zip(by_topic[rec.TOPIC_MR_IMAGE], image_rows, strict=True):
        k = row["slot"] - T0_SLOT
        assert msg.format == wire.JPEG_FORMAT and msg.header.frame_id == "camera_optical_frame"
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == log_time
        decoded = decode_jpeg(bytes(msg.data), expected_shape=(24, 32))
        assert np.abs(decoded.astype(int) - make_image(k)).mean() < 4
    cmd_rows = [r for k, r in enumerate(rows) if k != 4]
    for (_, msg), row in zip(by_topic[rec.TOPIC_CMD_VEL], cmd_rows, strict=True):
        k = row["slot"] - T0_SLOT
        assert msg.header.frame_id == "base_link"
        assert (msg.twist.linear.x, msg.twist.angular.z) == pytest.approx((0.1 * k, -0.05 * k))


def test_mcap_messages_are_valid_ros2_cdr(tmp_path: Path) -> None:
    """The raw payloads deserialize with rclpy's own typesupport, as ``ros2 bag play`` would do."""
    with RunRecorder(tmp_path) as recorder:
        recorder.write_slot(make_row(0), make_image(0), (0.3, 0.2))
    classes = {"sensor_msgs/msg/CompressedImage": CompressedImage,
               "geometry_msgs/msg/TwistStamped": TwistStamped, "std_msgs/msg/String": String}
    seen = set()
    with (tmp_path / "run.mcap").open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 3
        assert reader.get_header().profile == "ros2"
        for schema, channel, message in reader.iter_messages():
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            assert channel.metadata["offered_qos_profiles"] == "[]"  # required by the ros2 profile
            assert rec.TOPIC_TYPES[channel.topic] == schema.name
            msg = deserialize_message(message.data, classes[schema.name])
            seen.add(channel.topic)
            if channel.topic == rec.TOPIC_CMD_VEL:
                assert (msg.twist.linear.x, msg.twist.angular.z) == (0.3, 0.2)
            if channel.topic == rec.TOPIC_MR_IMAGE:
                assert decode_jpeg(bytes(msg.data)).shape == (24, 32, 3)
    assert seen == set(rec.TOPIC_TYPES)


def test_csv_value_rules(tmp_path: Path) -> None:
    with RunRecorder(tmp_path) as recorder:
        recorder.write_slot({"slot": 1, "loss": float("nan"), "psnr_db": float("inf"), "faults": ["a", "b"]},
                            None, None, stamp_ns=5)
        with pytest.raises(ValueError, match="unknown"):
            recorder.write_slot({"slot": 2, "lost": 1.0}, None, None)
        with pytest.raises(ValueError, match="source"):
            recorder.write_slot({"slot": 2, "source": "camera"}, None, None)
        with pytest.raises(ValueError, match="integer"):
            recorder.write_slot({"slot": 2, "bytes_sent": 1.5}, None, None)
        with pytest.raises(ValueError, match="required"):
            recorder.write_slot({"x": 1}, None, None)
        with pytest.raises(ValueError, match="pose key"):
            recorder.write_slot({"slot": 2, "x": 2}, None, None)
    rows = read_slots_csv(tmp_path / "slots.csv")
    assert len(rows) == 1  # refused rows left no trace
    assert rows[0]["loss"] is None and rows[0]["psnr_db"] == math.inf and rows[0]["faults"] == "a;b"
    (_, log_time, msg), = read_mcap(tmp_path / "run.mcap")
    assert log_time == 5
    assert json.loads(msg.data)["psnr_db"] is None and json.loads(msg.data)["faults"] == "a;b"


def test_a_slots_csv_recorded_before_the_last_columns_still_reads(tmp_path: Path) -> None:
    """A ``slots.csv`` written before ``scene_change`` was added (its header a prefix of today's) reads with the new
    column None; a header that is not such a prefix is refused."""
    old_columns = CSV_COLUMNS[:-1]
    path = tmp_path / "slots.csv"
    path.write_text(",".join(old_columns) + "\n" + "7,0.7,1" + "," * (len(old_columns) - 3) + "\n")
    (row,) = read_slots_csv(path)
    assert (row["slot"], row["x"], row["scene_change"]) == (7, 1, None)
    path.write_text(",".join(reversed(old_columns)) + "\n")
    with pytest.raises(ValueError, match="header"):
        read_slots_csv(path)


def test_extra_topics(tmp_path: Path) -> None:
    """Pose keys and schedules recorded with write_message land in the right segments and decode."""
    schedule = wire.ScheduleMsg(T0_SLOT, 0.1, 3, np.array([1, 0, 0], np.int8), np.array([0.1, 0.02, 0.02]))
    with RunRecorder(tmp_path, segment_slots=2) as recorder:
        recorder.write_message("/gsrmr/schedule", ros_wire.schedule_to_msg(schedule), T0_SLOT * SLOT_NS)
        for k in range(5):
            key = wire.PoseKey(T0_SLOT + k, 0.1 * k, 0.0, 0.5)
            recorder.write_message("/gsrmr/pose_key", ros_wire.pose_key_to_msg(key, CLOCK),
                                   CLOCK.start_ns(key.slot))
            recorder.write_slot(make_row(k), None, None)
        with pytest.raises(ValueError, match="recorded as"):
            recorder.write_message("/gsrmr/pose_key", String(data="x"), 0)
        with pytest.raises(ValueError, match="recorded as"):
            recorder.write_message(rec.TOPIC_SLOT_LOG, TwistStamped(), 0)
    with (tmp_path / "run.mcap").open("rb") as f:
        raw = [(c.topic, s.name, m.data) for s, c, m in make_reader(f).iter_messages()]
    keys = [deserialize_message(d, Vector3Stamped) for t, _, d in raw if t == "/gsrmr/pose_key"]
    assert [ros_wire.pose_key_from_msg(m, CLOCK).slot for m in keys] == [T0_SLOT + k for k in range(5)]
    (sched_data,) = [d for t, name, d in raw if t == "/gsrmr/schedule" and name == "std_msgs/msg/Float64MultiArray"]
    back = ros_wire.schedule_from_msg(deserialize_message(sched_data, Float64MultiArray))
    np.testing.assert_array_equal(back.x, schedule.x)
    decoded = read_mcap(tmp_path / "run.mcap")
    assert [t for t, _, _ in decoded].count("/gsrmr/pose_key") == 5


def test_recover_after_crash_between_rename_and_delete(tmp_path: Path) -> None:
    """run.mcap written but the segments not yet deleted: recovering again neither loses nor duplicates."""
    recorder = RunRecorder(tmp_path, segment_slots=2)
    for k in range(5):
        recorder.write_slot(make_row(k), make_image(k), None)
    recorder._finish_segment()  # what close() does before merging
    kept = {p.name: p.read_bytes() for p in tmp_path.glob("run-*.mcap")}
    assert len(kept) == 3
    recorder.close()
    for name, data in kept.items():
        (tmp_path / name).write_bytes(data)
    # The crash also cost a later segment's merge: drop slot 4 from run.mcap by rebuilding it from
    # the first two segments only, then recover from all three.
    (tmp_path / "run.mcap").unlink()
    (tmp_path / "run-0002.mcap").rename(tmp_path / "spare")
    rec.merge_segments(tmp_path, delete=False)
    (tmp_path / "spare").rename(tmp_path / "run-0002.mcap")
    assert recover_run(tmp_path) == tmp_path / "run.mcap"
    logs = [json.loads(m.data)["slot"] for t, _, m in read_mcap(tmp_path / "run.mcap") if t == rec.TOPIC_SLOT_LOG]
    assert logs == [T0_SLOT + k for k in range(5)]
    assert sum(t == rec.TOPIC_MR_IMAGE for t, _, _ in read_mcap(tmp_path / "run.mcap")) == 5


def test_torn_last_line_is_dropped(tmp_path: Path) -> None:
    path = tmp_path / "slots.csv"
    cells = dict.fromkeys(CSV_COLUMNS, "") | {"slot": "1", "stamp_s": "0.1", "x": "1", "source": "image"}
    path.write_text(",".join(CSV_COLUMNS) + "\n" + ",".join(cells.values()) + "\n2,0.2,0,0.0")
    rows = read_slots_csv(path)
    assert [r["slot"] for r in rows] == [1]
    path.write_text("slot,stamp\n1,2\n")
    with pytest.raises(ValueError, match="header"):
        read_slots_csv(path)


def test_lifecycle(tmp_path: Path) -> None:
    recorder = RunRecorder(tmp_path / "a")
    assert recorder.close() is None  # nothing recorded: no MCAP, header-only CSV
    assert recorder.close() is None
    assert read_slots_csv(tmp_path / "a" / "slots.csv") == []
    with pytest.raises(RuntimeError, match="closed"):
        recorder.write_slot({"slot": 0}, None, None)
    with pytest.raises(FileExistsError):
        RunRecorder(tmp_path / "a")
    for bad in ({"segment_slots": 0}, {"jpeg_quality": 0}):
        with pytest.raises(ValueError):
            RunRecorder(tmp_path / "b", **bad)


CRASH_SCRIPT = textwrap.dedent("""
    import sys, time
    import numpy as np
    from gsrmr_server.recording import RunRecorder
    out, stop_after = sys.argv[1], int(sys.argv[2])
    recorder = RunRecorder(out, segment_slots=5, chunk_bytes=4096)
    rng = np.random.default_rng(0)
    k = 0
    while True:
        image = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)  # noise: ~8 kB per JPEG
        recorder.write_slot({"slot": k, "stamp_s": k * 0.1, "x": 1, "source": "image"}, image, (0.1, 0.0))
        print(k, flush=True)
        k += 1
        if k == stop_after:
            time.sleep(60)  # killed here
""")


def run_and_kill(out: Path, stop_after: int, kill_when_rows: int) -> int:
    """Start a recorder process, SIGKILL it once it reported ``kill_when_rows`` slots; return that count."""
    proc = subprocess.Popen([sys.executable, "-c", CRASH_SCRIPT, str(out), str(stop_after)],
                            stdout=subprocess.PIPE, text=True, start_new_session=True)
    reported = -1
    try:
        deadline = time.monotonic() + 60
        while reported + 1 < kill_when_rows and time.monotonic() < deadline:
            line = proc.stdout.readline()  # type: ignore[union-attr]
            if not line:
                break
            reported = int(line)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        for line in proc.stdout:  # type: ignore[union-attr]
            reported = int(line)  # slots acknowledged between our decision and the kill
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()  # type: ignore[union-attr]
    assert proc.returncode == -signal.SIGKILL
    return reported + 1


@pytest.mark.parametrize(("stop_after", "kill_when_rows"), [(23, 23), (10**9, 17)],
                         ids=["idle", "mid-write"])
def test_kill_9_loses_no_written_slot(tmp_path: Path, stop_after: int, kill_when_rows: int) -> None:
    acknowledged = run_and_kill(tmp_path, stop_after, kill_when_rows)
    assert acknowledged >= kill_when_rows
    rows = read_slots_csv(tmp_path / "slots.csv")
    # Every slot write_slot returned from is in the CSV (at most one more the process was writing).
    assert [r["slot"] for r in rows][:acknowledged] == list(range(acknowledged))
    assert len(rows) <= acknowledged + 1
    finished = sorted(p.name for p in tmp_path.glob("run-*.mcap"))
    assert len(finished) >= acknowledged // 5 - 1 >= 2
    # Every finished segment is a complete MCAP that decodes without the .part.
    slots_in_segments = []
    for name in finished:
        for topic, _, msg in read_mcap(tmp_path / name):
            if topic == rec.TOPIC_SLOT_LOG:
                slots_in_segments.append(json.loads(msg.data)["slot"])
    assert slots_in_segments == list(range(5 * len(finished)))
    # Recovery merges them plus the complete chunks of the open segment into run.mcap.
    merged = recover_run(tmp_path)
    assert merged == tmp_path / "run.mcap"
    assert not list(tmp_path.glob("run-*"))
    logs = [json.loads(m.data)["slot"] for t, _, m in read_mcap(merged) if t == rec.TOPIC_SLOT_LOG]
    images = [m for t, _, m in read_mcap(merged) if t == rec.TOPIC_MR_IMAGE]
    assert logs == list(range(len(logs))) and 5 * len(finished) <= len(logs) <= len(rows)
    assert len(images) >= 5 * len(finished)
    for msg in images:
        assert decode_jpeg(bytes(msg.data)).shape == (48, 64, 3)
    assert recover_run(tmp_path) is None  # nothing left to recover


def test_cli_recover_and_info(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run_and_kill(tmp_path, 12, 12)
    assert rec.main(["recover", str(tmp_path)]) == 0
    assert "recovered" in capsys.readouterr().out
    assert rec.main(["info", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "/gsrmr/slot_log [std_msgs/msg/String]" in out and "12 slot rows" in out
    assert rec.main(["recover", str(tmp_path)]) == 0
    assert "nothing to recover" in capsys.readouterr().out


def test_concurrent_writers_keep_rows_whole(tmp_path: Path) -> None:
    import threading

    def writer(offset: int) -> None:
        for k in range(offset, offset + 25):
            recorder.write_slot(make_row(k), make_image(k), (0.1, 0.0))

    with RunRecorder(tmp_path, segment_slots=7) as recorder:
        threads = [threading.Thread(target=writer, args=(o,)) for o in (0, 100)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    rows = read_slots_csv(tmp_path / "slots.csv")
    expected = sorted(T0_SLOT + k for o in (0, 100) for k in range(o, o + 25))
    assert sorted(r["slot"] for r in rows) == expected
    assert all(r == {**make_row(r["slot"] - T0_SLOT), "faults": r["faults"]} for r in rows)
    logs = [json.loads(m.data)["slot"] for t, _, m in read_mcap(tmp_path / "run.mcap") if t == rec.TOPIC_SLOT_LOG]
    assert sorted(logs) == expected
