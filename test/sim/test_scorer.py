"""The simulation's scorer (gsrmr-sim-scorer): its backlog, scores.csv and the report's join, the wait for it, its
place in the process list, and the node itself fed through its callbacks (scores, truth folder, model reload)."""

from __future__ import annotations

import signal
import threading
import time

from conftest import ros_env
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from support.stack_harness import make_point_model

from gsrmr_common.camera import CameraMount
from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.ros_wire import camera_info_from_intrinsics, image_to_msg, ledger_to_msg, mr_slot_info_to_msg
from gsrmr_common.slot_clock import SlotClock
from gsrmr_common.tf_tree import CAMERA_OPTICAL_FRAME
from gsrmr_common.wire import LedgerRow, MRSlotInfo, PoseKey, RealSource
from gsrmr_server.recording import read_slots_csv, write_slots_csv
from gsrmr_server.scoring import SlotScorer
from gsrmr_server.server_params import ServerParameters
from gsrmr_server.slot_core import build_composer, build_server_core
from gsrmr_server.slot_row import SCORE_COLUMNS, SlotScore
from gsrmr_server.uplink import SlotUploads
from gsrmr_sim.scores import SCORER_READY_NAME, SCORES_NAME, ScoresWriter, await_scores, join_scores, read_scores
from gsrmr_sim.sim_stack import SCORER_NICE, WORLD_NICE, sim_stack
from gsrmr_sim.truth_frames import TruthFrameWriter
from gsrmr_sim.world import Round2Record, load_scene, record_round2, with_resolution
from gsrmr_sim.world.scorer_core import ScoreBacklog
from gsrmr_sim.world.scorer_node import ScorerNode
from gsrmr_splat.model import GaussianModel

CLOCK = SlotClock(0.1)


def _ledger(slot: int, frame_stamp_s: float = float("nan")) -> LedgerRow:
    return LedgerRow(slot, 0, 0.0, 192, 1e-6, 0.0, 0.0, 8000, 0.0, frame_stamp_s)


def _info(slot: int) -> MRSlotInfo:
    return MRSlotInfo.of(slot, RealSource.RENDER, PoseKey(slot, 0.0, 0.0, 0.0), 0.1 * slot)


def test_backlog_pairs_image_and_record_and_waits_briefly_for_the_ledger_row():
    backlog = ScoreBacklog(CLOCK, depth_slots=10, ledger_grace_s=0.5)
    img = np.zeros((2, 2, 3), np.uint8)
    backlog.add_info(_info(5), now_s=0.0)  # the record may come first
    assert backlog.take(0.0) is None and backlog.waiting() == 1
    backlog.add_image(CLOCK.start_ns(5) - 3_000, img, now_s=0.0)  # a stamp a few µs early still names slot 5
    backlog.add_image(CLOCK.start_ns(6), img, now_s=0.0)
    backlog.add_info(_info(6), now_s=0.0)
    backlog.add_ledger(_ledger(6, 0.55))
    assert backlog.take(0.1) is None  # slot 5 (oldest) has no ledger row yet: in slot order, it waits
    job = backlog.take(0.6)  # … for ledger_grace_s at most
    assert (job.info.slot, job.stamp_ns, job.ledger) == (5, CLOCK.start_ns(5) - 3_000, None)
    job = backlog.take(0.6)
    assert job.info.slot == 6 and job.ledger == _ledger(6, 0.55) and backlog.take(0.6) is None
    backlog.add_image(CLOCK.start_ns(7), img, now_s=1.0)
    backlog.add_info(_info(7), now_s=1.0)
    assert backlog.take(1.0) is None and backlog.take(1.0, flush=True).info.slot == 7


def test_backlog_holds_slots_back_while_the_server_streams():
    """With idle_s nothing is scored while MR images keep coming (scoring would compete with the system under
    test); once the stream pauses for idle_s — or three quarters of the depth wait — the slots come out in order."""
    backlog = ScoreBacklog(CLOCK, depth_slots=8, ledger_grace_s=0.0, idle_s=0.5)
    img = np.zeros((2, 2, 3), np.uint8)
    for i, slot in enumerate(range(10, 15)):  # one slot every 0.1 s
        backlog.add_image(CLOCK.start_ns(slot), img, now_s=0.1 * i)
        backlog.add_info(_info(slot), now_s=0.1 * i)
        assert backlog.streaming(0.1 * i) and backlog.take(0.1 * i) is None
    assert backlog.take(0.8) is None  # 0.4 s after the last image: still streaming
    assert not backlog.streaming(0.9)
    assert [backlog.take(0.9).info.slot for _ in range(5)] == [10, 11, 12, 13, 14]
    for slot in range(20, 26):  # 6 ready ≥ 0.75 × 8: the backlog is handed out although images keep coming
        backlog.add_image(CLOCK.start_ns(slot), img, now_s=2.0)
        backlog.add_info(_info(slot), now_s=2.0)
    assert not backlog.streaming(2.0) and backlog.take(2.0).info.slot == 20
    assert backlog.streaming(2.0) and backlog.take(2.0) is None  # 5 left: below the mark again
    assert backlog.take(2.0, flush=True).info.slot == 21  # flush: at once


def test_backlog_holds_a_round_drops_past_its_depth_and_keeps_the_frames_still_needed():
    backlog = ScoreBacklog(CLOCK, depth_slots=3, frame_margin_s=0.15)
    for slot in range(100, 105):  # 5 slots paired, depth 3: the 2 oldest dropped
        backlog.add_image(CLOCK.start_ns(slot), np.zeros((2, 2, 3), np.uint8), now_s=0.0)
        backlog.add_info(_info(slot), now_s=0.0)
    assert backlog.dropped == 2 and backlog.waiting() == 3
    frames = {slot: np.full((2, 2, 3), slot % 256, np.uint8) for slot in range(98, 106)}
    for slot, frame in frames.items():  # one frame 10 ms after each slot start
        backlog.add_frame(CLOCK.start_ns(slot) + 10_000_000, frame)
    backlog.add_ledger(_ledger(103, (CLOCK.start_ns(102) + 10_000_000) / 1e9))  # 103 used 102's frame
    backlog.add_ledger(_ledger(104, (CLOCK.start_ns(100) + 10_000_000) / 1e9))  # 104 names a frame long gone
    job = backlog.take(0.0, flush=True)
    # without a ledger row: the newest frame by 5 ms after the slot start (102's, captured at +10 ms, is not)
    assert job.info.slot == 102 and job.ledger is None and job.frame is frames[101]
    job = backlog.take(0.0)
    assert job.info.slot == 103 and job.frame is frames[102]  # the frame the robot's row names
    # frames from 0.15 s before the oldest slot still to score are kept: 100's was gone (oldest waiting: 102)
    assert backlog.take(0.0).frame is None


def test_scores_csv_round_trips_continues_and_joins_the_servers_rows_by_slot(tmp_path):
    writer = ScoresWriter(tmp_path)
    writer.write(SlotScore(7, 0.0125, 31.5, 0.93, 0.02, 0.0125))
    writer.write(SlotScore(8))  # composed, not measured (no true frame)
    writer.close()
    again = ScoresWriter(tmp_path)  # a restarted scorer continues the file
    again.write(SlotScore(9, 0.5, 10.0, 0.1))
    again.close()
    assert (tmp_path / SCORES_NAME).read_text().splitlines()[0] == ",".join(SCORE_COLUMNS)
    scores = read_scores(tmp_path)
    assert scores[7] == {"slot": 7, "loss": 0.0125, "psnr_db": 31.5, "ssim": 0.93, "gs_truth_loss": 0.02,
                         "image_truth_loss": 0.0125}
    assert scores[8]["loss"] is None and scores[9]["gs_truth_loss"] is None
    rows = [{"slot": s, "stamp_s": 0.1 * s, "source": "render", "loss": None} for s in (6, 7, 8, 9)]
    joined = join_scores(rows, tmp_path)
    assert [r["loss"] for r in joined] == [None, 0.0125, None, 0.5] and rows[1]["loss"] is None  # copies
    assert joined[1]["gs_truth_loss"] == 0.02 and joined[0]["stamp_s"] == rows[0]["stamp_s"]
    write_slots_csv(tmp_path / "slots.csv", joined)  # the report's slots.csv: the server's columns, filled
    assert read_slots_csv(tmp_path / "slots.csv")[1]["psnr_db"] == 31.5
    assert join_scores(rows, tmp_path / "none") == rows
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / SCORES_NAME).write_text("slot,x\n")
    with pytest.raises(ValueError, match="header"):
        ScoresWriter(tmp_path / "other")


class _Proc:
    """A supervised process as await_scores sees it."""

    def __init__(self) -> None:
        self.signals: list[int] = []
        self.returncode: int | None = None

    def poll(self) -> int | None:
        return self.returncode

    def send_signal(self, sig: int) -> None:
        self.signals.append(sig)


class _Stack:
    def __init__(self, names: list[str]) -> None:
        self.procs = {name: _Proc() for name in names}


def test_await_scores_stops_the_others_then_waits_for_every_slot_or_gives_up(tmp_path):
    stack = _Stack(["gsrmr_server", "gsrmr_sim_scorer", "gsrmr_mock_camera"])
    writer = ScoresWriter(tmp_path)

    def score_late() -> None:
        for slot in range(10, 16):
            time.sleep(0.1)
            writer.write(SlotScore(slot, 0.01, 30.0, 0.9))

    worker = threading.Thread(target=score_late)
    worker.start()
    lines: list[str] = []
    missing = await_scores(stack, {"gsrmr_sim_scorer": (tmp_path, range(10, 16))}, stall_s=5, log=lines.append)
    worker.join()
    assert missing == {"gsrmr_sim_scorer": []} and not lines
    assert stack.procs["gsrmr_server"].signals == [signal.SIGINT] == stack.procs["gsrmr_mock_camera"].signals
    assert stack.procs["gsrmr_sim_scorer"].signals == []
    # a scorer that stops making progress: the wait ends after stall_s and says what is missing
    t0 = time.monotonic()
    missing = await_scores(stack, {"gsrmr_sim_scorer": (tmp_path, range(10, 18))}, stall_s=1.0, log=lines.append)
    assert missing == {"gsrmr_sim_scorer": [16, 17]} and 1.0 <= time.monotonic() - t0 < 5
    assert "2 of the round's 8 composed slots have no score" in lines[-1]
    stack.procs["gsrmr_sim_scorer"].returncode = 1  # a scorer that died: no wait at all
    t0 = time.monotonic()
    assert await_scores(stack, {"gsrmr_sim_scorer": (tmp_path, [99])}, stall_s=30, log=lines.append) == \
        {"gsrmr_sim_scorer": [99]}
    assert time.monotonic() - t0 < 2
    writer.close()


def test_await_scores_reads_the_rows_a_scorer_flushed_as_it_exited(tmp_path):
    """The race of a bench run (idle, 1 of 3): the wait read the file, the scorer flushed its last 6 rows and
    exited, and the poll saw it gone: 6 slots were reported missing that the file held."""
    stack = _Stack(["gsrmr_sim_scorer"])
    writer = ScoresWriter(tmp_path)
    writer.write(SlotScore(10, 0.01, 30.0, 0.9))
    scorer = stack.procs["gsrmr_sim_scorer"]

    def poll() -> int:  # the exit: the last rows land just before the poll that sees it
        writer.write(SlotScore(11, 0.01, 30.0, 0.9))
        writer.close()
        return 0

    scorer.poll = poll
    assert await_scores(stack, {"gsrmr_sim_scorer": (tmp_path, [10, 11])}, stall_s=30) == {"gsrmr_sim_scorer": []}


def test_the_scorer_runs_beside_the_server_with_what_the_server_composes_with():
    specs = {s.name: s for s in sim_stack(model_path="/m.ply", record_dir="/rec", truth_dir="/truth",
                                           overrides={"gsrmr_server": {"mr_content": "/other.yaml",
                                                                       "jpeg_quality": 70}})}
    server, scorer = specs["gsrmr_server"], specs["gsrmr_sim_scorer"]
    assert (scorer.executable, scorer.host, scorer.nice) == ("gsrmr-sim-scorer", "server", SCORER_NICE) != WORLD_NICE
    shared = ("model_path", "mr_content", "background_rgb", *CameraMount().as_parameters())
    assert {k: scorer.params[k] for k in shared} == {k: server.params[k] for k in shared}
    assert scorer.params["mr_content"] == "/other.yaml" and "jpeg_quality" not in scorer.params
    assert (scorer.params["record_dir"], scorer.params["truth_dir"]) == ("/rec", "/truth")
    assert scorer.params["hindsight_jpeg_quality"] == 80  # the robot's (config/robot.yaml)
    for gone in ("evaluate_ground_truth", "hindsight_jpeg_quality", "ground_truth_dir", "truth_dir"):
        assert gone not in server.params


@pytest.fixture(scope="module")
def round2(tmp_path_factory):
    """A recorded round of the sandbox at 64×48, two small models and a server core composing on the first."""
    scene = with_resolution(load_scene("sandbox"), 64, 48)
    tmp = tmp_path_factory.mktemp("scorer")
    record = Round2Record(record_round2(scene, tmp, slots=6, seed=0))
    models = [make_point_model(tmp / name, n=1500, seed=seed) for name, seed in (("a", 0), ("b", 1))]
    return scene, record, models


def _scorer_node(ctx: Context, scene, mount: CameraMount, model, tmp_path, **params) -> ScorerNode:
    values = {"model_path": str(model), "mr_content": scene.mr_content,
              "background_rgb": [float(c) for c in scene.background], "hindsight_jpeg_quality": 80,
              "record_dir": str(tmp_path), **params}
    values.update(mount.as_parameters())
    return ScorerNode(worker=False, context=ctx,
                      parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])


@pytest.mark.ros
def test_scorer_node_scores_each_published_slot_and_follows_a_model_change(round2, tmp_path):
    """Fed as over DDS (the server's mr/image and mr/slot_info, the robot's ledger and camera_info, the camera's
    frames or the truth folder), the node writes the library's scores; a new model_path is loaded for the next
    slot; a model file that does not exist is refused."""
    scene, record, (model_a, model_b) = round2
    params = ServerParameters(model_path=str(model_a), mr_content=scene.mr_content,
                              background_rgb=tuple(scene.background), camera_mount=record.mount)
    server = build_server_core(params, GaussianModel.load_ply(model_a), record.intrinsics, warm_up=False)

    def library(model) -> SlotScorer:
        return SlotScorer(build_composer(GaussianModel.load_ply(model), record.intrinsics,
                                         mr_content=scene.mr_content, mount=record.mount,
                                         background_rgb=tuple(scene.background), warm_up=False), 80)

    frames = [np.clip(np.rint(record[t].image * 255.0), 0, 255).astype(np.uint8) for t in range(len(record))]
    stamps = [CLOCK.start_ns(1000 + t) - 20_000_000 for t in range(len(record))]  # captured 20 ms before

    def slot(t: int):
        key = PoseKey(1000 + t, *map(float, record.poses[t]))
        jpeg = encode_jpeg(frames[t], 80) if t % 2 == 0 else None
        return server.process(SlotUploads(1000 + t, key=key, jpeg=jpeg), None, time_s=float(record.times_s[t]),
                              stamp_s=0.0)

    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env()["ROS_DOMAIN_ID"]))
    truth = TruthFrameWriter(tmp_path / "truth")
    try:
        topic = _scorer_node(ctx, scene, record.mount, model_a, tmp_path / "topic")
        folder = _scorer_node(ctx, scene, record.mount, model_a, tmp_path / "folder", truth_dir=str(tmp_path / "truth"))
        info = camera_info_from_intrinsics(record.intrinsics, 0, CAMERA_OPTICAL_FRAME)
        outs = []
        assert not (tmp_path / "topic" / SCORER_READY_NAME).exists()  # the runner waits until the images arrive
        for t in range(4):
            out = slot(t)
            outs.append(out)
            ledger = ledger_to_msg(_ledger(1000 + t, stamps[t] / 1e9))
            for node in (topic, folder):
                node.on_mr_image(image_to_msg(out.mr_u8, CLOCK.start_ns(1000 + t), CAMERA_OPTICAL_FRAME))
                node.on_slot_info(mr_slot_info_to_msg(out.info))
                node.on_ledger(ledger)
            topic.on_camera(image_to_msg(frames[t], stamps[t], CAMERA_OPTICAL_FRAME))
            truth.put(stamps[t], frames[t])
            if t == 0:
                assert topic.score_ready(flush=True) == 0  # nothing before the robot's calibration
                topic.use_camera_info(info)
                folder.use_camera_info(info)
            if t == 2:  # the server's model changes: the scorer is told, and scores slot 2 on with it
                assert not topic.set_parameters([Parameter("model_path", value=str(tmp_path / "no.ply"))])[0] \
                    .successful
                assert topic.set_parameters([Parameter("model_path", value=str(model_b))])[0].successful
            assert topic.score_ready(flush=True) == 1
        assert folder.score_ready(flush=True) == 4
        assert (tmp_path / "topic" / SCORER_READY_NAME).exists()
        want_a, want_b = library(model_a), library(model_b)
        expected = [want_a.score(o.info, o.mr_u8, frames[t]) for t, o in enumerate(outs)]
        assert [SlotScore(**r) for r in read_scores(tmp_path / "folder").values()] == expected
        got = [SlotScore(**r) for r in read_scores(tmp_path / "topic").values()]
        assert got[:2] == expected[:2]
        assert got[2:] == [want_b.score(o.info, o.mr_u8, frames[t + 2]) for t, o in enumerate(outs[2:])]
        assert got[2] != expected[2]  # the other model's GS composite gives other hindsight losses
        assert all(s.scored and s.gs_truth_loss is not None for s in got) and topic.scored == 4
        topic.on_shutdown()
        folder.on_shutdown()
        topic.destroy_node()
        folder.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
