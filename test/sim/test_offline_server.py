"""The live slot core run offline over a recorded round (gsrmr_sim.offline_server), the survey built on it, and
the robot's replayed odometry (gsrmr_sim.world.reported_pose). Pure: no ROS."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gsrmr_common.metrics import image_quality
from gsrmr_server.mr.blend import jpeg_mr_loss, mr_image
from gsrmr_sim.offline_server import TRUE, OfflineServer
from gsrmr_sim.survey import gs_losses
from gsrmr_sim.world import Round2Record, load_scene, record_round2, with_resolution
from gsrmr_sim.world.kinematics import drive_route, start_pose
from gsrmr_sim.world.reported_pose import pose_errors, reported_poses
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render

SLOTS = 12


@pytest.fixture(scope="module")
def scene():
    return with_resolution(load_scene("sandbox"), 96, 72)


@pytest.fixture(scope="module")
def record(tmp_path_factory, scene) -> Round2Record:
    return Round2Record(record_round2(scene, tmp_path_factory.mktemp("r2"), slots=SLOTS, seed=0))


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> GaussianModel:
    import sys

    sys.path.insert(0, str(Path(__file__).parents[1]))
    from support.stack_harness import make_point_model

    return GaussianModel.load_ply(make_point_model(tmp_path_factory.mktemp("m"), n=3000))


@pytest.fixture(scope="module")
def server(record, model, scene) -> OfflineServer:
    return OfflineServer(record, model, mr_content=scene.mr_content, background_rgb=scene.background, jpeg_quality=80)


def _u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)


def test_key_slot_at_the_true_pose_is_an_independent_composite_scored_in_8_bit(server, record, model, scene):
    got = server.evaluate(["key"] * SLOTS, pose=TRUE)
    for t in (0, 5, SLOTS - 1):
        rec = record[t]
        gs = render(model, rec.camera, scene.background)
        depth = np.where(gs.alpha > 0.5, gs.depth, np.inf).astype(np.float32)
        v, d = server.core.composer.virtual.render(rec.camera, time_s=rec.time_s, real_depth_m=depth)
        truth = mr_image(rec.image, v, d)
        want = image_quality(truth, _u8(mr_image(gs.rgb, v, d)).astype(np.float32) / 255.0)
        assert got[t].loss == pytest.approx(want["loss"], abs=1e-6)
        assert got[t].psnr_db == pytest.approx(want["psnr_db"], abs=1e-4)


def test_image_slot_carries_the_robots_jpeg_loss(server, record):
    q = server.evaluate(["image"] * SLOTS)
    for t in (0, 7):
        uploads, best = next(server._replay(["image"] * (t + 1), "reported", t))
        assert uploads.jpeg is not None and uploads.key is not None
        c = server.outcome(uploads, best).composed
        assert c.source == "image"
        assert q[t].loss > 0.0  # JPEG is lossy: an image slot is not scored as m̂ = m
        # the loss the server's hindsight column computes (float composite), up to the published 8 bits
        j = jpeg_mr_loss(_u8(record[t].image), c.virtual, c.mask, 80)
        assert q[t].loss == pytest.approx(j, abs=2e-3)


def test_undelivered_slots_use_the_live_fallback_pose(server):
    # nothing ever arrived: the background colour (the live server's "none"); after keys, the last key
    # extrapolated at the recent velocity (UplinkAssembler.best_pose), so it differs from a stale pose
    first = server.evaluate(["none", "key"])
    assert first[0].loss > 0
    moving = server.evaluate(["key", "key", "key", "none", "none"])
    stale = server.evaluate(["key", "none", "none", "none", "none"])
    assert moving[4] != stale[4]
    assert server.evaluate(["key", "key", "key", "key", "key"])[3] != moving[3]


def test_unknown_delivery_and_wrong_length_are_refused(server):
    with pytest.raises(ValueError, match="unknown delivery"):
        server.evaluate(["key", "photo"])
    with pytest.raises(ValueError, match="slots"):
        server.evaluate(["key"] * (SLOTS + 1))


def test_survey_is_the_offline_core(server, record, model, scene):
    sl = gs_losses(record, model, scene.background, mr_content=scene.mr_content, jpeg_quality=80)
    keys = server.evaluate(["key"] * SLOTS, pose=TRUE)
    images = server.evaluate(["image"] * SLOTS)
    assert [s.loss for s in sl] == [k.loss for k in keys]
    assert [s.image_loss for s in sl] == [i.loss for i in images]
    assert np.allclose([s.pose for s in sl], record.poses)


def test_reported_poses_replay_the_odometry_of_the_drive(scene):
    drive = drive_route(scene.route, 120, scene.slot_s, pose0=start_pose(scene.route, scene.route.start_jitter_m, 0))
    rep = reported_poses(drive, scene.slot_s)
    err = pose_errors(rep, drive.poses)
    assert np.allclose(rep[0], drive.poses[0])
    # the world's only odometry errors are the wire's quantisation: sub-millimetre over 12 s, but not zero
    assert 0 < err["position_max_m"] < 2e-3 and err["heading_max_rad"] < 1e-3
    assert np.array_equal(rep, reported_poses(drive, scene.slot_s))  # deterministic
