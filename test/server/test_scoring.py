"""The deployment's scoring library (gsrmr_server.scoring) and the MR slot info the server publishes for it.

Behaviour unchanged: for image, render, fallback, refused and pose-less slots of a small model, the scores the
simulation's scorer rebuilds from the published record alone (:class:`SlotScorer`, its own composer) are, bit for
bit, what the server's ``ServerCore.score`` gave before scoring left the server — reproduced here by a verbatim
copy of that code (:func:`_score_as_the_server_did`), kept only in this test.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from support.stack_harness import make_point_model

from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.link_model import required_power_w
from gsrmr_common.metrics import image_quality
from gsrmr_common.ros_wire import image_from_msg, image_to_msg, mr_slot_info_from_msg, mr_slot_info_to_msg
from gsrmr_common.wire import POSE_KEY_BITS, REAL_SOURCES, LedgerRow, MRSlotInfo, PoseKey, RealSource
from gsrmr_server.compose import to_u8
from gsrmr_server.mr.blend import jpeg_mr_loss, mr_image
from gsrmr_server.scoring import SlotScorer, reference_quality, score_slot
from gsrmr_server.server_params import ServerParameters
from gsrmr_server.slot_core import SlotOutcome, build_composer, build_server_core
from gsrmr_server.slot_row import SCORE_COLUMNS, SLOT_ROW_COLUMNS, SlotScore
from gsrmr_server.uplink import SlotUploads
from gsrmr_sim.world import Round2Record, load_scene, record_round2, with_resolution
from gsrmr_splat.model import GaussianModel

ROBOT_JPEG_QUALITY = 80


def _truth_quality_as_the_server_did(result, mr_u8: np.ndarray, frame: np.ndarray) -> dict[str, float] | None:
    """Verbatim: ``gsrmr_server.slot_core.truth_quality`` before scoring left the server."""
    if frame.shape[:2] != result.mr.shape[:2]:
        return None
    truth = mr_image(frame.astype(np.float32) / 255.0, result.virtual, result.mask)
    return image_quality(truth, np.asarray(mr_u8, np.float32) / 255.0)


def _score_as_the_server_did(outcome: SlotOutcome, truth_frame: np.ndarray | None,
                             hindsight_jpeg_quality: int | None) -> dict[str, float]:
    """Verbatim but for returning the columns instead of writing them into the row: ``ServerCore.score``."""
    quality = _truth_quality_as_the_server_did(outcome.composed, outcome.mr_u8, truth_frame) \
        if truth_frame is not None else None
    if quality is None:
        return {}
    extra: dict[str, float] = {}
    c = outcome.composed
    if hindsight_jpeg_quality is not None and c.gs_mr is not None:
        truth = mr_image(truth_frame.astype(np.float32) / 255.0, c.virtual, c.mask)
        gs_u8 = outcome.mr_u8 if c.source != "image" else to_u8(c.gs_mr)
        extra["gs_truth_loss"] = image_quality(truth, gs_u8.astype(np.float32) / 255.0)["loss"]
        if c.source == "image":
            extra["image_truth_loss"] = quality["loss"]
        else:
            extra["image_truth_loss"] = jpeg_mr_loss(truth_frame, c.virtual, c.mask, hindsight_jpeg_quality)
    return {"loss": quality["loss"], "psnr_db": quality["psnr_db"], "ssim": quality["ssim"], **extra}


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A recorded round of the sandbox at 64×48 (virtual agents in view in its first slots) and a small model."""
    scene = with_resolution(load_scene("sandbox"), 64, 48)
    tmp = tmp_path_factory.mktemp("scoring")
    record = Round2Record(record_round2(scene, tmp, slots=8, seed=0))
    return scene, record, make_point_model(tmp, n=2000)


def _params(scene, record, model_path: Path) -> ServerParameters:
    return ServerParameters(model_path=str(model_path), mr_content=scene.mr_content,
                            background_rgb=tuple(scene.background), camera_mount=record.mount)


def _slots(record) -> list[tuple[SlotUploads, PoseKey | None, LedgerRow | None]]:
    """Image, image without its key, render, fallback (nothing arrived), refused JPEG and pose-less slots."""
    def key(t: int, da: float = 0.0) -> PoseKey:
        a, b, th = record.poses[t]
        return PoseKey(t, float(a) + da, float(b), float(th))

    def frame(t: int) -> np.ndarray:
        return np.clip(np.rint(record[t].image * 255.0), 0, 255).astype(np.uint8)

    def ledger(t: int, x: int) -> LedgerRow:
        return LedgerRow(t, x, 0.0, POSE_KEY_BITS + 8000 * x, 2e-6, 0.0, 0.0, 8000, 0.0, float(record.times_s[t]))

    jpeg = lambda t: encode_jpeg(frame(t), ROBOT_JPEG_QUALITY)  # noqa: E731
    small = encode_jpeg(np.zeros((10, 10, 3), np.uint8), 90)
    return [(SlotUploads(0, key=key(0), jpeg=jpeg(0)), None, ledger(0, 1)),
            (SlotUploads(1, jpeg=jpeg(1)), key(0, 0.02), ledger(1, 1)),
            (SlotUploads(2, key=key(2)), None, ledger(2, 0)),
            (SlotUploads(3), key(2, 0.03), None),
            (SlotUploads(4, key=key(4), jpeg=small), None, ledger(4, 1)),
            (SlotUploads(5), None, None)]


@pytest.mark.parametrize("hindsight", [ROBOT_JPEG_QUALITY, None])
def test_the_scorer_gives_what_the_servers_scoring_gave_bit_for_bit(world, hindsight):
    scene, record, model_path = world
    params = _params(scene, record, model_path)
    server = build_server_core(params, GaussianModel.load_ply(model_path), record.intrinsics)
    # the scorer's composer: its own model load and MR content, as the scorer node builds it
    scorer = SlotScorer(build_composer(GaussianModel.load_ply(model_path), record.intrinsics,
                                       mr_content=params.mr_content, mount=params.camera_mount,
                                       background_rgb=params.background_rgb, render_threads=1), hindsight)
    sources = []
    for uploads, best, ledger in _slots(record):
        t = uploads.slot
        out = server.process(uploads, best, time_s=float(record.times_s[t]), stamp_s=0.1 * t, ledger=ledger)
        truth = np.clip(np.rint(record[t].image * 255.0), 0, 255).astype(np.uint8)
        want = _score_as_the_server_did(out, truth, hindsight)
        # what crosses DDS: the MR image as sensor_msgs/Image, the record as Float64MultiArray
        mr_u8 = image_from_msg(image_to_msg(out.mr_u8, 0, "camera_optical_frame"))
        info = mr_slot_info_from_msg(mr_slot_info_to_msg(out.info))
        got = scorer.score(info, mr_u8, truth)
        assert got == SlotScore(t, **want), (t, out.composed.source)
        assert score_slot(out.composed, out.mr_u8, truth, hindsight) == got  # the library on the server's slot
        sources.append(str(out.composed.source))
        assert got.loss is not None and (got.gs_truth_loss is not None) == (hindsight is not None and t != 5)
    assert sources == ["image", "image", "render", "fallback", "fallback", "none"]
    first = _slots(record)[0][0]
    composed = server.process(first, None, time_s=float(record.times_s[0]), stamp_s=0.0).composed
    assert (composed.mask < 0.5).any(), "no virtual agent in view: the test would not exercise v and d"


def test_mr_slot_info_carries_source_pose_and_content_time_and_refuses_nonsense():
    key = PoseKey(7, 1.5, -0.25, 0.125)
    info = MRSlotInfo.of(7, RealSource.FALLBACK, key, 3.2, level=1)
    assert info.to_data() == [7.0, float(REAL_SOURCES.index(RealSource.FALLBACK)), 1.5, -0.25, 0.125, 3.2, 1.0]
    assert MRSlotInfo.from_data(info.to_data()) == info and info.pose == key
    assert MRSlotInfo.from_data(info.to_data()[:6]) == replace(info, level=0)  # a server without levels
    blind = MRSlotInfo.of(8, RealSource.NONE, None, 0.0)
    assert blind.pose is None and MRSlotInfo.from_data(blind.to_data()).pose is None and blind.level == 0
    msg = mr_slot_info_to_msg(info)
    assert [(d.label, d.size) for d in msg.layout.dim] == [("mr_slot_info", 7)]
    for bad in ([7.0, 9.0, 0.0, 0.0, 0.0, 0.0],  # no such source
                [7.0, 1.0, float("nan"), 0.0, 0.0, 0.0],  # a render needs a pose
                [7.0, 1.0, 0.0, 0.0, 0.0],  # too short
                [7.0, 1.0, 0.0, 0.0, 0.0, 0.0, 3.0],  # no such level
                [7.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.5],
                [float("inf"), 1.0, 0.0, 0.0, 0.0, 0.0]):
        with pytest.raises(ValueError):
            MRSlotInfo.from_data(bad)


def test_scores_need_a_reference_of_the_images_size_and_an_image_that_fits_the_intrinsics(world):
    scene, record, model_path = world
    params = _params(scene, record, model_path)
    server = build_server_core(params, GaussianModel.load_ply(model_path), record.intrinsics, warm_up=False)
    out = server.process(_slots(record)[2][0], None, time_s=0.0, stamp_s=0.2)
    scorer = SlotScorer(server.composer, ROBOT_JPEG_QUALITY)
    assert scorer.score(out.info, out.mr_u8, None) == SlotScore(2)
    assert scorer.score(out.info, out.mr_u8, np.zeros((2, 2, 3), np.uint8)) == SlotScore(2)
    assert reference_quality(out.mr_u8, out.composed.virtual, out.composed.mask, np.zeros((2, 2, 3), np.uint8)) is None
    with pytest.raises(ValueError, match="intrinsics"):
        scorer.score(out.info, out.mr_u8[:-1], np.zeros((47, 64, 3), np.uint8))
    assert not SlotScore(3).scored and set(SCORE_COLUMNS) <= set(SLOT_ROW_COLUMNS)  # the report's columns


def test_hindsight_columns_say_what_either_choice_would_have_left(world):
    """An image slot's image_truth_loss is its own loss, a key slot's gs_truth_loss its own; a key slot's JPEG
    alternative is the true frame at the robot's quality, as an image slot got it; energies stay the server's."""
    scene, record, model_path = world
    server = build_server_core(_params(scene, record, model_path), GaussianModel.load_ply(model_path),
                               record.intrinsics, warm_up=False)
    rng = np.random.default_rng(1)
    frame = rng.integers(0, 255, (48, 64, 3), np.uint8)  # random pixels: the GS render is poor
    key = PoseKey(0, *map(float, record.poses[0]))
    g = 2e-6
    img_led = LedgerRow(0, 1, 0.0, 8 * 1000 + POSE_KEY_BITS, g, 0.0, 0.0, 8000, 0.0, 0.7)
    img = server.process(SlotUploads(0, key=key, jpeg=encode_jpeg(frame, ROBOT_JPEG_QUALITY)), None, time_s=0.0,
                         stamp_s=0.0, ledger=img_led)
    r = img.row
    assert r.energy_image_j == pytest.approx(0.1 * required_power_w(8000 + POSE_KEY_BITS, g, 0.1, 1e6, 1e-9))
    assert r.energy_key_j == pytest.approx(0.1 * required_power_w(POSE_KEY_BITS, g, 0.1, 1e6, 1e-9))
    assert r.loss is None and r.gs_truth_loss is None  # the server scores nothing
    s_img = score_slot(img.composed, img.mr_u8, frame, ROBOT_JPEG_QUALITY)
    assert s_img.image_truth_loss == s_img.loss and s_img.gs_truth_loss > s_img.image_truth_loss
    ks = server.process(SlotUploads(1, key=PoseKey(1, key.a_m, key.b_m, key.theta_rad)), None, time_s=0.0,
                        stamp_s=0.1)
    s_key = score_slot(ks.composed, ks.mr_u8, frame, ROBOT_JPEG_QUALITY)
    assert ks.composed.source == "render" and s_key.gs_truth_loss == s_key.loss
    assert s_key.image_truth_loss == pytest.approx(s_img.image_truth_loss, rel=1e-6)
    assert score_slot(ks.composed, ks.mr_u8, frame).gs_truth_loss is None  # hindsight off
