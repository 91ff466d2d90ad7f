"""The server's localizer: a received image registered in its worker process gives the correction that undoes the
key's error; registrations are rationed."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from gsrmr_common.camera import CameraMount, Intrinsics, camera_from_pose
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import PoseKey
from gsrmr_server.localizer import SKIP_BUSY, SKIP_INTERVAL, SKIP_LATE, ServerLocalizer, wait_until_ready
from gsrmr_sim.shared_data import garden_model
from gsrmr_splat.render import render

MOUNT = CameraMount(height_m=0.5, pitch_rad=math.radians(20), forward_m=0.0)
K = Intrinsics.from_fov(320, 240, math.radians(70))
TRUE = Pose2D(1.3, 0.1, math.pi)  # the robot at the garden's table, looking at it


@pytest.fixture(scope="module")
def garden(tmp_path_factory):
    model = garden_model()
    path = model.save_ply(tmp_path_factory.mktemp("localizer") / "model.ply")
    image = render(model, camera_from_pose(*TRUE, MOUNT, K)).rgb
    return path, (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)


def test_a_registered_image_corrects_the_key(garden):
    path, image = garden
    loc = ServerLocalizer(str(path), MOUNT, (0.0, 0.0, 0.0))
    try:
        assert wait_until_ready(loc)
        key = Pose2D(1.33, 0.08, math.pi + math.radians(1.0))  # the odometry's belief, 3.6 cm and 1° off
        assert loc.offer(image, PoseKey(1, *key), 0, K, stamp_s=1.0, now_s=1.0, late=False)
        assert not loc.offer(image, PoseKey(2, *key), 0, K, stamp_s=1.1, now_s=1.1, late=False)  # one at a time
        correction = None
        for _ in range(400):
            correction = loc.poll(2.0)
            if correction is not None:
                break
            time.sleep(0.05)
        assert correction is not None and correction.seq == 1
        corrected = correction.x.compose(key)  # the robot's next keys: X ∘ (what it believed)
        assert corrected.distance_m(TRUE) < 0.005 and abs(corrected.heading_error_rad(TRUE)) < math.radians(0.1)
        assert not loc.offer(image, PoseKey(3, *key), 1, K, stamp_s=1.5, now_s=1.5, late=False)  # within 1 s
        assert not loc.offer(image, PoseKey(4, *key), 1, K, stamp_s=3.0, now_s=3.5, late=True)  # the server is late
        assert loc.skipped == {SKIP_BUSY: 1, SKIP_INTERVAL: 1, SKIP_LATE: 1}
        values = loc.diagnostic_values(3.5)
        assert values["localization"] == "tracking" and values["correction_seq"] == 1
    finally:
        loc.close()
