"""``gsrmr-localize``: a dataset's frames refined against the model, written as a dataset; refusals and bad input."""

from __future__ import annotations

import csv
import json
import math

import cv2
import numpy as np
import pytest

from gsrmr_common.camera import Camera
from gsrmr_common.nerfstudio import DatasetFrame, read_dataset, write_dataset
from gsrmr_offline.localize_cli import main
from gsrmr_sim.shared_data import garden_model, load_garden
from gsrmr_splat.render import render


@pytest.fixture(scope="module")
def garden(tmp_path_factory):
    """The garden model, a dataset of its renders at three cameras (true poses) and the same moved 4 cm / 1.5°."""
    model = garden_model()
    _, _, cams = load_garden()
    root = tmp_path_factory.mktemp("localize")
    model_path = model.save_ply(root / "model.ply")
    frames = []
    for cam in cams:
        small = Camera(cam.intrinsics.scaled(324, 210), cam.world_to_camera)
        frames.append(DatasetFrame(small, render(model, small).rgb, pose=(0.0, 0.0, 0.0)))
    write_dataset(root / "truth", frames)
    meta = json.loads((root / "truth" / "transforms.json").read_text())
    rng = np.random.default_rng(3)
    for entry in meta["frames"]:
        c2w = np.asarray(entry["transform_matrix"], np.float64)
        c2w[:3, 3] += 0.04 * rng.normal(size=3) / math.sqrt(3)
        c2w[:3, :3] = cv2.Rodrigues(rng.normal(size=3) / math.sqrt(3) * math.radians(1.5))[0] @ c2w[:3, :3]
        entry["transform_matrix"] = c2w.tolist()
        entry["keep_me"] = 7  # a key of the dataset's own: kept
    moved = root / "moved"
    moved.mkdir()
    (moved / "transforms.json").write_text(json.dumps(meta))
    (moved / "images").symlink_to(root / "truth" / "images")
    return model_path, root / "truth", moved


def test_the_frames_come_back_to_their_true_poses(garden, tmp_path, capsys):
    model_path, truth, moved = garden
    assert main([str(model_path), str(moved), "--out", str(tmp_path / "out")]) == 0
    assert "3 of 3 frames registered" in capsys.readouterr().out
    got, want = read_dataset(tmp_path / "out"), read_dataset(truth)
    for g, w in zip(got, want, strict=True):
        assert np.linalg.norm(g.camera.camera_to_world[:3, 3] - w.camera.camera_to_world[:3, 3]) < 0.003
        assert g.file_path == w.file_path and g.image.shape == w.image.shape  # OUT is a usable dataset
    meta = json.loads((tmp_path / "out" / "transforms.json").read_text())
    assert all(f["keep_me"] == 7 for f in meta["frames"])
    rows = list(csv.DictReader((tmp_path / "out" / "localize.csv").open()))
    assert [r["status"] for r in rows] == ["accepted"] * 3 and all(float(r["seconds"]) > 0 for r in rows)


def test_planar_keeps_the_mount_and_moves_the_robot_pose(garden, tmp_path, capsys):
    model_path, _truth, moved = garden
    assert main([str(model_path), str(moved), "--out", str(tmp_path / "out"), "--planar"]) == 0
    meta = json.loads((tmp_path / "out" / "transforms.json").read_text())
    before = json.loads((moved / "transforms.json").read_text())
    for after, was in zip(meta["frames"], before["frames"], strict=True):
        a, b = np.asarray(after["transform_matrix"]), np.asarray(was["transform_matrix"])
        # the mount is fixed: the camera moved by a planar motion only (its height and tilt did not change)
        assert a[2, 3] == pytest.approx(b[2, 3], abs=1e-6)
        assert a[2, :3] == pytest.approx(b[2, :3], abs=1e-6)
        assert after["gsrmr_pose"] != [0.0, 0.0, 0.0]


def test_bad_input_is_one_line_and_a_nonzero_exit(garden, tmp_path, capsys):
    model_path, _truth, moved = garden
    assert main([str(tmp_path / "none.ply"), str(moved), "--out", str(tmp_path / "a")]) == 2
    assert "cannot load the model" in capsys.readouterr().err
    no_images = tmp_path / "no_images"
    no_images.mkdir()
    (no_images / "transforms.json").write_text((moved / "transforms.json").read_text())
    assert main([str(model_path), str(no_images), "--out", str(tmp_path / "b")]) == 2
    assert "no frame" in capsys.readouterr().err
    assert main([str(model_path), str(tmp_path), "--out", str(tmp_path / "c")]) == 2
    assert "cannot read the dataset" in capsys.readouterr().err
