"""gsrmr-survey: the scheduler's seed loss map from the robot's mapping round (gsrmr_offline.deployment_survey).

The world here is a point model of the sandbox (``make_point_model``): its renders along the sandbox route, at the
configured camera mount, are the dataset's frames, so the model itself is a perfect model of them and another
random point cloud an untrained one. Pure: no ROS. Tiny images (64×48), a few frames.
"""

from __future__ import annotations

import csv
from dataclasses import replace
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from support.stack_harness import make_point_model

from gsrmr_common.camera import CameraMount, Intrinsics, camera_from_pose
from gsrmr_common.nerfstudio import DatasetFrame, read_dataset, write_dataset
from gsrmr_common.wire import PoseKey
from gsrmr_offline.deployment_survey import (
    frame_at_width,
    frame_mount,
    recorded_split,
    route_time_s,
    select_frames,
    survey_frames,
)
from gsrmr_offline.frame_loss import frame_loss
from gsrmr_offline.survey_cli import default_config_path, main, mount_from_file, route_from_file
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import OnlinePlanner
from gsrmr_scheduler.scheduler_params import SchedulerParameters
from gsrmr_server.compose import MRComposer
from gsrmr_server.slot_core import build_composer
from gsrmr_sim.survey import gs_losses
from gsrmr_sim.world import Round2Record, load_scene, record_round2, with_resolution
from gsrmr_splat.datasets import render_views
from gsrmr_splat.model import GaussianModel

FRAMES, HOLDOUT_EVERY = 8, 4  # held out: frames 3 and 7
BACKGROUND = (0.5, 0.55, 0.6)  # config/server.yaml's background_rgb, the CLI's default
K = Intrinsics.from_fov(64, 48, 1.2)


def route_poses(n: int) -> list[tuple[float, float, float]]:
    """``n`` poses evenly spaced along the sandbox route (config/routes/sandbox.yaml), facing along it."""
    path = route_from_file(default_config_path("sandbox", "routes")).path
    s = np.linspace(0.0, path.length_m, n, endpoint=False)
    return [(float(x), float(y), float(path.heading_at(v))) for (x, y), v in zip(path.points_at(s), s, strict=True)]


def write_world_dataset(folder: Path, world: Path, *, with_pose: bool = True, intrinsics: Intrinsics = K) -> Path:
    """The world model's renders at the route poses, camera = pose ∘ config/camera_mount.yaml (8-bit PNGs)."""
    mount = mount_from_file(default_config_path("camera_mount"))
    poses = route_poses(FRAMES)
    views = render_views(GaussianModel.load_ply(world), [camera_from_pose(*p, mount, intrinsics) for p in poses],
                         BACKGROUND, with_depth=False)
    write_dataset(folder, [replace(f, pose=p if with_pose else None) for f, p in zip(views, poses, strict=True)])
    return folder


def write_train_record(model: Path, holdout_every: int, train: int, held: int) -> None:
    """A train.json beside ``model`` as gsrmr_sim.models.build_model writes it (the parts the survey reads)."""
    (model.parent / "train.json").write_text(json.dumps({"recipe": {"holdout_every": holdout_every},
                                                         "train_frames": train, "heldout_frames": held}))


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> dict[str, Path]:
    """A dataset of the world, the world model (trained with every 4th frame held out) and an untrained model."""
    base = tmp_path_factory.mktemp("site")
    (base / "perfect").mkdir()
    (base / "untrained").mkdir()
    perfect = make_point_model(base / "perfect", n=1500, seed=0)
    untrained = make_point_model(base / "untrained", n=1500, seed=1)
    for model in (perfect, untrained):
        write_train_record(model, HOLDOUT_EVERY, FRAMES - FRAMES // HOLDOUT_EVERY, FRAMES // HOLDOUT_EVERY)
    return {"dataset": write_world_dataset(base / "ds", perfect), "perfect": perfect, "untrained": untrained,
            "base": base}


def rows(out: Path) -> list[dict[str, str]]:
    with Path(f"{out}.frames.csv").open() as fh:
        return list(csv.DictReader(fh))


def survey(model: Path, dataset: Path, out: Path, *extra: str) -> int:
    return main([str(model), str(dataset), "--out", str(out), "--width", "64", *extra])


@pytest.fixture(scope="module")
def surveys(site) -> dict[str, Path]:
    """The CLI run on the perfect and on the untrained model (defaults: held-out views, robot's JPEG q80)."""
    out = {}
    for name in ("perfect", "untrained"):
        out[name] = site["base"] / f"{name}.json"
        assert survey(site[name], site["dataset"], out[name]) == 0
    return out


def test_perfect_model_loses_nothing_an_untrained_one_clearly_more(surveys):
    perfect, untrained = (rows(surveys[n]) for n in ("perfect", "untrained"))
    for r in perfect:
        assert float(r["loss"]) < 0.002  # only the frames' 8-bit PNGs differ from the renders
        assert float(r["camera_vs_mount_m"]) < 1e-6 and float(r["camera_vs_mount_deg"]) < 1e-4
    for p, u in zip(perfect, untrained, strict=True):
        assert float(u["loss"]) > 0.05 and float(u["loss"]) > 20 * float(p["loss"])
        # an image slot leaves the JPEG's loss: more than a perfect render, less than an untrained one
        assert float(p["loss"]) < float(p["image_loss"]) < float(u["loss"])
    maps = {n: LossMap.load(surveys[n]) for n in surveys}
    assert maps["perfect"].image_loss == pytest.approx(np.mean([float(r["image_loss"]) for r in perfect]), abs=1e-6)
    # the live server's sample reads the JPEG's error above the loss against the frame: for a perfect model nearly
    # all of the sample is that error; the map keeps the mean as its sample_offset
    for r in perfect:
        assert 0.5 * float(r["image_loss"]) < float(r["sample_bias"]) <= float(r["image_loss"]) + 0.002
    for name, got in (("perfect", perfect), ("untrained", untrained)):
        assert maps[name].sample_offset == pytest.approx(np.mean([float(r["sample_bias"]) for r in got]), abs=1e-6)


def test_cells_are_keyed_by_gsrmr_pose_and_hold_the_frames_losses(site, surveys):
    got = rows(surveys["untrained"])
    assert [r["file"] for r in got] == ["images/frame_00003.png", "images/frame_00007.png"]  # held out only
    assert {r["split"] for r in got} == {"held-out"}
    poses = {f.file_path: f.pose for f in read_dataset(site["dataset"], load_images=False)}
    lm = LossMap.load(surveys["untrained"])
    assert set(lm.cells) == {lm.key(*poses[r["file"]]) for r in got}
    for r in got:
        assert [float(r[c]) for c in ("a_m", "b_m", "theta_rad")] == pytest.approx(poses[r["file"]], abs=1e-6)
        assert lm.predict(*poses[r["file"]]) == pytest.approx(float(r["loss"]), abs=1e-6)
        # the content time is where the route passes the frame at its nominal speed
        assert float(r["content_time_s"]) == pytest.approx(route_time_s(route_from_file(
            default_config_path("sandbox", "routes")), poses[r["file"]]), abs=1e-3)
    assert lm.prior == SchedulerParameters().loss_prior


def test_the_scheduler_takes_the_map(site, surveys):
    lm = LossMap.load(surveys["untrained"])  # what scheduler_node does with its loss_map_file
    params = SchedulerParameters()
    config = params.planner_config(lm)
    assert config.image_slot_loss == lm.image_loss > 0  # image_slot_loss −1: the map's measured image loss
    assert lm.sample_offset is not None  # loss_sample_offset −1: the map's measured sample offset
    assert params.with_values({"loss_sample_offset": -1.0}).planner_config(lm).loss_sample_offset == lm.sample_offset
    planner = OnlinePlanner(config, route_from_file(default_config_path("sandbox", "routes")), lm, params.link)
    held = read_dataset(site["dataset"], load_images=False)[HOLDOUT_EVERY - 1]
    surveyed = {r["file"]: float(r["loss"]) for r in rows(surveys["untrained"])}
    assert planner.loss_map.predict(*held.pose) == pytest.approx(surveyed[held.file_path], abs=1e-6)


def test_training_views_are_refused_unless_allowed(site, tmp_path, capsys):
    (tmp_path / "all").mkdir()
    model = tmp_path / "all" / "m.ply"
    model.write_bytes(site["perfect"].read_bytes())
    write_train_record(model, 0, FRAMES, 0)  # gsrmr-train without --holdout-every: every frame trained on
    assert survey(model, site["dataset"], tmp_path / "m.json") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "held out no frame" in err and "--allow-training-views" in err
    assert survey(model, site["dataset"], tmp_path / "m.json", "--allow-training-views") == 0
    captured = capsys.readouterr()
    assert "optimistic" in captured.err and "8 frames surveyed" in captured.out
    assert {r["split"] for r in rows(tmp_path / "m.json")} == {"training"}
    # a second lap the model was not trained on: every frame, no warning
    assert survey(model, site["dataset"], tmp_path / "lap.json", "--all-frames") == 0
    assert capsys.readouterr().err == ""
    assert len(rows(tmp_path / "lap.json")) == FRAMES


def test_bad_input_is_one_line_and_exit_2(site, tmp_path, capsys):
    def model_copy(name: str) -> Path:
        (tmp_path / name).mkdir()
        path = tmp_path / name / "model.ply"
        path.write_bytes(site["perfect"].read_bytes())
        return path

    no_record = model_copy("no_record")  # no train.json beside it
    odd = model_copy("odd")
    write_train_record(odd, 2, 6, 2)  # a split the dataset does not give (every 2nd frame: 4 + 4)
    no_pose = write_world_dataset(tmp_path / "no_pose", site["perfect"], with_pose=False)
    distorted = write_world_dataset(tmp_path / "distorted", site["perfect"])
    meta = json.loads((distorted / "transforms.json").read_text())
    (distorted / "transforms.json").write_text(json.dumps({**meta, "k1": 0.05}))
    cases = {  # what the one line must say (its fix) → (model, dataset, extra arguments)
        "does not exist": (tmp_path / "missing.ply", site["dataset"], ()),
        "no transforms.json": (site["perfect"], tmp_path / "nowhere", ()),
        "carries gsrmr_pose": (site["perfect"], no_pose, ()),
        "--holdout-every N": (no_record, site["dataset"], ()),
        "not rectified": (site["perfect"], distorted, ()),
        "drop --holdout-every": (site["perfect"], site["dataset"], ("--holdout-every", "8")),
        "records 6 + 2": (odd, site["dataset"], ()),
    }
    for fix, (model, dataset, extra) in cases.items():
        assert survey(model, dataset, tmp_path / "x.json", *extra) == 2, fix
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and err.startswith("gsrmr-survey: error: ") and fix in err, (fix, err)
    assert not (tmp_path / "x.json").exists()
    # without a record, --holdout-every names the split
    assert survey(no_record, site["dataset"], tmp_path / "h.json", "--holdout-every", "4") == 0
    assert [r["file"] for r in rows(tmp_path / "h.json")] == ["images/frame_00003.png", "images/frame_00007.png"]


def test_a_frame_without_gsrmr_pose_is_skipped_and_counted(site):
    frames = read_dataset(site["dataset"], load_images=False)
    frames[HOLDOUT_EVERY - 1] = replace(frames[HOLDOUT_EVERY - 1], pose=None)
    sel = select_frames(frames, split=recorded_split(site["perfect"]))
    assert [s.index for s in sel.frames] == [2 * HOLDOUT_EVERY - 1] and sel.without_pose == 1


def test_frames_are_scaled_to_the_uplink_width_never_enlarged():
    rng = np.random.default_rng(0)
    frame = DatasetFrame(camera_from_pose(0.0, 0.0, 0.0, CameraMount(), Intrinsics.from_fov(128, 96, 1.2)),
                         rng.uniform(0, 1, (96, 128, 3)).astype(np.float32), pose=(0.0, 0.0, 0.0))
    half = frame_at_width(frame, 64)
    assert half.image.shape == (48, 64, 3) and half.camera.intrinsics == frame.camera.intrinsics.scaled(64, 48)
    assert np.array_equal(half.image, cv2.resize(frame.image, (64, 48), interpolation=cv2.INTER_AREA))
    assert frame_at_width(frame, 320) is frame  # the server never renders more pixels than the robot sends


def test_the_frames_own_camera_is_rendered():
    mount = CameraMount(height_m=0.2, pitch_rad=0.1, forward_m=0.05, left_m=-0.02, roll_rad=0.01, yaw_rad=-0.03)
    pose = (0.4, -0.3, 2.0)
    camera = camera_from_pose(*pose, mount, K)
    got = frame_mount(camera, pose)
    for name in ("height_m", "pitch_rad", "forward_m", "left_m", "roll_rad", "yaw_rad"):
        assert getattr(got, name) == pytest.approx(getattr(mount, name), abs=1e-12), name
    assert np.allclose(camera_from_pose(*pose, got, K).world_to_camera, camera.world_to_camera, atol=1e-12)


def test_content_time_follows_the_route_at_its_nominal_speed():
    route = route_from_file(default_config_path("sandbox", "routes"))
    path = route.path
    assert route_time_s(route, (*path.point_at(0.0), 0.0)) == pytest.approx(0.0, abs=0.02)
    half = (*path.point_at(0.5 * path.length_m), 0.0)
    assert route_time_s(route, half) == pytest.approx(0.5 * path.length_m / route.speed_mps, abs=0.05)


def test_the_simulators_survey_is_the_deployment_function(tmp_path):
    """The same true frames scored by gs_losses (the demo's seed map, the experiments' L_t and J_t) and by the
    deployment survey of a nerfstudio dataset holding them give the same L and J."""
    scene = with_resolution(load_scene("sandbox"), 64, 48)
    record = Round2Record(record_round2(scene, tmp_path / "r1", slots=3, round_index=1))
    model_path = make_point_model(tmp_path, n=1500, seed=2)
    model = GaussianModel.load_ply(model_path)
    sim = gs_losses(record, model, scene.background, mr_content=scene.mr_content, jpeg_quality=80)
    poses = [tuple(float(v) for v in p) for p in record.poses]
    write_dataset(tmp_path / "ds", [DatasetFrame(record.camera(t), record[t].image, pose=poses[t])
                                    for t in range(len(record))])
    selection = select_frames(read_dataset(tmp_path / "ds", load_images=False), split=None, all_frames=True)
    base = build_composer(model, K, mr_content=scene.mr_content, mount=record.mount,
                          background_rgb=tuple(scene.background), warm_up=False)
    dep = survey_frames(selection.frames, base, dataset=tmp_path / "ds", width_px=64, jpeg_quality=80,
                        content_times_s=list(record.times_s), mount=record.mount)
    for s, d in zip(sim, dep, strict=True):
        assert d.pose == pytest.approx(s.pose, abs=1e-12)
        assert d.score.loss == pytest.approx(s.loss, abs=1e-6) and s.loss > 0.01
        assert d.score.image_loss == pytest.approx(s.image_loss, abs=1e-6) and s.image_loss > 0
        assert d.score.sample_bias == pytest.approx(s.sample_bias, abs=1e-6) and math.isfinite(s.sample_bias)
        assert d.camera_vs_mount_m < 1e-9
    # the frame-level function both call: the record's own frame, pose and mount give gs_losses' numbers exactly
    composer = MRComposer(model, base.virtual, record.intrinsics, record.mount, tuple(scene.background))
    direct = frame_loss(composer, np.clip(np.rint(record[1].image * 255), 0, 255).astype(np.uint8),
                        PoseKey(1, *poses[1]), content_time_s=float(record.times_s[1]), jpeg_quality=80)
    assert (direct.loss, direct.psnr_db, direct.image_loss, direct.sample_bias) == \
        (sim[1].loss, sim[1].psnr_db, sim[1].image_loss, sim[1].sample_bias)
