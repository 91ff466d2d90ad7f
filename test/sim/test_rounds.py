"""gsrmr_sim.rounds: what the next round's seed map is surveyed on (held-out views only, none superseded)."""

from __future__ import annotations

import numpy as np

from gsrmr_common.camera import Intrinsics
from gsrmr_common.nerfstudio import DatasetFrame, read_dataset, write_dataset
from gsrmr_sim.rounds import survey_frames
from gsrmr_splat.datasets import orbit_cameras


def _frames(cameras, shade: float) -> list[DatasetFrame]:
    k = cameras[0].intrinsics
    return [DatasetFrame(c, np.full((k.height, k.width, 3), shade, np.float32), pose=(float(i), 0.0, 0.0))
            for i, c in enumerate(cameras)]


def test_the_survey_set_is_the_unsuperseded_held_out_mapping_frames_and_the_held_out_received_ones(tmp_path):
    k = Intrinsics.from_fov(16, 12, 1.2)
    mapping_cams = orbit_cameras(32, k)  # every 8th (7, 15, 23, 31) held out from the model's training
    write_dataset(tmp_path / "mapping", _frames(mapping_cams, 0.2))
    # the round: 20 received frames, the last 16 held out by the update; one of them sees mapping frame 15 again
    received_cams = [mapping_cams[15], *orbit_cameras(19, k, radius_m=3.0)]
    write_dataset(tmp_path / "received", _frames(received_cams, 0.8))
    out = survey_frames(tmp_path / "mapping", tmp_path / "received", tmp_path / "survey", holdout_every=8)
    frames = read_dataset(out)
    mapping = [f for f in frames if float(f.image.mean()) < 0.5]
    received = [f for f in frames if float(f.image.mean()) > 0.5]
    assert sorted(int(f.pose[0]) for f in mapping) == [7, 23, 31]  # 15 superseded: it shows the old world
    assert sorted(int(f.pose[0]) for f in received) == list(range(4, 20))  # the update's held-out 16
