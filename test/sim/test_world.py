"""Simulated world: scene validation, ray-cast geometry, occlusion mask, route, recorder, CLI (no ROS)."""

from __future__ import annotations

import copy
import math
import sys

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
import yaml

from gsrmr_common.camera import Camera, CameraMount, camera_from_pose
from gsrmr_common.nerfstudio import read_dataset
from gsrmr_common.route import LoopPath, PurePursuit
from gsrmr_sim.world import cli
from gsrmr_sim.world.kinematics import drive_route, lap_time_s, start_pose, unicycle_step
from gsrmr_sim.world.points import find_points_file, make_world
from gsrmr_sim.world.raycast import RayCastWorld
from gsrmr_sim.world.recorder import Round2Record, record_round1, record_round2, with_resolution
from gsrmr_sim.world.scene import SceneError, load_scene, parse_scene, resolve_scene_path
from gsrmr_sim.world.virtual import virtual_view

MINIMAL = {"route": {"waypoints": [[0, 0], [1, 0], [1, 1]]}}


def _scene(**extra: object) -> dict:
    data = copy.deepcopy(MINIMAL)
    data.update(copy.deepcopy(extra))
    return data


# ---------------------------------------------------------------------------------------------- scene


def test_minimal_scene_gets_documented_defaults():
    s = parse_scene(_scene())
    k = s.camera.intrinsics
    assert (k.width, k.height) == (320, 240)
    assert math.isclose(2 * math.atan(0.5 * k.width / k.fx), math.radians(70.0))
    assert s.camera.mount.height_m == 0.15 and math.isclose(s.camera.mount.pitch_rad, math.radians(5))
    assert s.camera.rate_hz == 10.0 and s.slot_s == 0.1 and s.slots == 288
    assert s.room is not None and s.objects == () and s.events == ()


@pytest.mark.parametrize(("patch", "message"), [
    ({"objects": [{"position": [0, 0]}, {"position": [1, 1]},
                  {"position": [0, 1], "size": [0.1, -0.2, 0.3]}]},
     "objects[2].size: must be 3 positive numbers"),
    ({"objects": [{"position": [0, 0], "colour": [1, 0, 0]}]}, "objects[0].colour: unknown key"),
    ({"camera": {"mount": {"pitch_deg": 95}}}, "camera.mount.pitch_deg: must be ≤ 80"),
    ({"camera": {"widht": 100}}, "camera.widht: unknown key"),
    ({"lights": [{"type": "point"}]}, "lights[0].position: is required for a point light"),
    ({"objects": [{"position": [0, 0], "material": {"color": [2, 0, 0]}}]},
     "objects[0].material.color: must be 3 numbers in [0, 1]"),
    ({"objects": [{"position": [0, 0], "material": {"texture": "marble"}}]},
     "objects[0].material.texture: must be one of"),
    ({"events": [{"type": "move", "object": "ghost", "from_s": 1.0, "position": [0, 0]}]},
     "events[0].object: no object with id 'ghost'"),
    ({"events": [{"type": "light", "light": "ambient", "from_s": 2.0, "to_s": 1.0}]},
     "events[0].to_s: must be > from_s"),
    ({"virtual_agents": []}, "virtual_agents: unknown key"),  # the server's MR content (config/mr), not the world's
    ({"objects": [{"id": "a", "position": [0, 0]}, {"id": "a", "position": [1, 0]}]},
     "objects[1].id: duplicate id 'a'"),
    ({"teleporter": True}, "teleporter: unknown key"),
    ({"objects": [{"position": [0, 0], "path": {"waypoints": [[0, 0], [1, 0]]}}]}, "objects[0].path: unknown key"),
    ({"objects": [{"position": [0, 0], "shape": "cylinder", "size": [1, 1, 1]}]},
     "objects[0].size: not allowed for a cylinder"),
])
def test_bad_scene_values_are_errors_naming_the_key(patch, message):
    with pytest.raises(SceneError) as info:
        parse_scene(_scene(**patch))
    assert str(info.value).startswith(message), str(info.value)


def test_missing_route_and_bad_route_entries_name_the_key():
    with pytest.raises(SceneError, match=r"^route: is required"):
        parse_scene({})
    with pytest.raises(SceneError, match=r"^route\.waypoints\[1\]: must be 2 numbers"):
        parse_scene({"route": {"waypoints": [[0, 0], [1, "x"], [1, 1]]}})


def test_scene_file_errors_carry_the_file_and_key(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(_scene(ambient=-1)))
    with pytest.raises(SceneError, match=r"bad\.yaml: ambient: must be ≥ 0"):
        load_scene(str(bad))


def test_shipped_scenes_load_by_name():
    sandbox = load_scene("sandbox")
    assert resolve_scene_path("sandbox").name == "sandbox.yaml"
    assert sandbox.mr_content == "sandbox" and len(virtual_view(sandbox).content.agents) == 2
    assert sandbox.slots == 288 and sandbox.slot_s == 0.1
    assert {ev.type for ev in sandbox.events} >= {"move", "light", "add", "region_light"}
    assert math.dist(sandbox.server_position_m[:2], (0.0, 0.0)) == pytest.approx(10.0, abs=1.0)
    garden = load_scene("garden")
    assert garden.points is not None and find_points_file(garden.points.path).exists()


def test_scene_names_resolve_from_the_install_share_dir_without_the_source_tree(tmp_path, monkeypatch):
    from gsrmr_sim.world import scene as scene_mod

    share = tmp_path / "share" / "gsrmr" / "config" / "scenes"
    share.mkdir(parents=True)
    (share / "sandbox.yaml").write_text(resolve_scene_path("sandbox").read_text())
    monkeypatch.setattr(scene_mod, "REPO_SCENES_DIR", tmp_path / "no_repo")
    monkeypatch.setattr(sys, "prefix", str(tmp_path))
    found = resolve_scene_path("sandbox")
    assert found.exists() and "no_repo" not in str(found)
    assert load_scene("sandbox").name == "sandbox"
    with pytest.raises(FileNotFoundError, match="no scene named 'nowhere'"):
        resolve_scene_path("nowhere")


def test_events_apply_only_in_round_two_and_only_in_their_span():
    s = load_scene("sandbox")
    lamp = {lt.id: lt for lt in s.lights}["lamp"]
    at = {lt.id: lt for lt in s.state_at(2, 18.0).lights}["lamp"]
    assert at.intensity == pytest.approx(3.0 * lamp.intensity)
    assert {lt.id: lt for lt in s.state_at(2, 21.0).lights}["lamp"].intensity == lamp.intensity
    assert {lt.id: lt for lt in s.state_at(1, 18.0).lights}["lamp"].intensity == lamp.intensity
    moved = {o.id: o for o in s.state_at(2, 10.0).objects}["crate_b"]
    assert moved.position == (-1.5, 0.7)
    assert "dropped_bag" in {o.id for o in s.state_at(2, 25.0).objects}
    assert "dropped_bag" not in {o.id for o in s.state_at(2, 22.0).objects}


def test_a_persistent_change_happens_in_its_round_and_stays_in_every_later_one():
    """from_round k: absent in the mapping round and scored rounds < k, from from_s in round k, from the start of
    every later one; an event without from_round restarts with every scored round."""
    s = parse_scene(_scene(objects=[{"id": "box", "position": [1.0, 0.0], "size": [0.2, 0.2, 0.2]}], events=[
        {"type": "move", "object": "box", "from_s": 5.0, "from_round": 2, "position": [0.0, 1.0]},
        {"type": "remove", "object": "box", "from_s": 1.0, "to_s": 2.0}]))

    def box(round_index: int, t_s: float):
        return {o.id: o.position for o in s.state_at(round_index, t_s).objects}.get("box")

    assert box(1, 10.0) == (1.0, 0.0)  # mapping round
    assert box(2, 10.0) == (1.0, 0.0)  # scored round 1: not yet
    assert box(3, 4.0) == (1.0, 0.0) and box(3, 6.0) == (0.0, 1.0)  # scored round 2: from from_s
    assert box(4, 0.0) == (0.0, 1.0) and box(9, 0.0) == (0.0, 1.0)  # later rounds: from the start
    assert box(2, 1.5) is None and box(7, 1.5) is None and box(7, 2.5) == (0.0, 1.0)  # transient: every round


def test_a_walker_crosses_and_is_gone_and_a_flicker_toggles():
    s = parse_scene(_scene(lights=[{"id": "lamp", "type": "point", "position": [0, 0, 1], "intensity": 0.5}],
                           events=[{"type": "walker", "from_s": 2.0, "to_s": 4.0, "position": [2.0, 0.0],
                                    "shape": {"id": "person", "position": [0.0, 0.0], "size": [0.3, 0.3, 0.9]}},
                                   {"type": "flicker", "light": "lamp", "from_s": 10.0, "to_s": 12.0,
                                    "intensity_scale": 0.1, "period_s": 0.5}]))

    def person(t_s: float):
        return {o.id: o.position for o in s.state_at(2, t_s).objects}.get("person")

    def lamp(t_s: float) -> float:
        return {lt.id: lt.intensity for lt in s.state_at(2, t_s).lights}["lamp"]

    assert person(1.9) is None and person(2.0) == (0.0, 0.0) and person(3.0) == pytest.approx((1.0, 0.0))
    assert person(4.0) is None and person(3.0) == pytest.approx((1.0, 0.0)) and s.state_at(1, 3.0).objects == ()
    assert lamp(9.9) == 0.5 and lamp(10.1) == pytest.approx(0.05) and lamp(10.3) == 0.5 and lamp(10.6) == \
        pytest.approx(0.05) and lamp(12.1) == 0.5


@pytest.mark.parametrize(("event", "message"), [
    ({"type": "move", "object": "box", "from_s": 0.0, "to_s": 3.0, "from_round": 1, "position": [0, 0]},
     r"events\[0\]\.from_round: marks a persistent change"),
    ({"type": "walker", "from_s": 0.0, "position": [0, 0], "shape": {"position": [1, 1], "size": [1, 1, 1]}},
     r"events\[0\]\.to_s: is required for a walker"),
    ({"type": "walker", "from_s": 0.0, "to_s": 2.0, "shape": {"position": [1, 1], "size": [1, 1, 1]}},
     r"events\[0\]\.position: is required for a walker"),
    ({"type": "flicker", "light": "nope", "from_s": 0.0, "to_s": 2.0}, r"events\[0\]\.light: no light"),
    ({"type": "move", "object": "box", "from_s": 0.0, "from_round": 0, "position": [0, 0]},
     r"events\[0\]\.from_round"),
    ({"type": "move", "object": "box", "from_s": 1.0, "from_round": 1, "position": [0, 0], "round_shift_s": [2.0]},
     r"events\[0\]\.round_shift_s: a non-empty list"),
    ({"type": "move", "object": "box", "from_s": 1.0, "to_s": 3.0, "position": [0, 0], "round_shift_s": []},
     r"events\[0\]\.round_shift_s: a non-empty list"),
    ({"type": "move", "object": "box", "from_s": 1.0, "to_s": 3.0, "position": [0, 0], "round_shift_s": [0, -2]},
     r"events\[0\]\.round_shift_s: shifts the event before the round starts"),
])
def test_bad_round_and_transient_events_are_refused_with_their_path(event, message):
    with pytest.raises(SceneError, match=message):
        parse_scene(_scene(objects=[{"id": "box", "position": [1.0, 0.0], "size": [0.2, 0.2, 0.2]}],
                           events=[event]))


def test_the_changed_and_transient_sandboxes_map_the_same_world_as_the_sandbox():
    """Same mapping round (the model and its survey are the sandbox's); the changed one's changes persist from
    scored round 1, the transient one's restart with every round, each round at another time (round_shift_s)."""
    base, changed, transient = (load_scene(n) for n in ("sandbox", "sandbox_changed", "sandbox_transient"))
    for t_s in (0.0, 10.0, 25.0):
        assert changed.state_at(1, t_s) == base.state_at(1, t_s) == transient.state_at(1, t_s)
    assert all(ev.persistent for ev in changed.events) and not any(ev.persistent for ev in transient.events)
    for round_index in (2, 3, 5):
        objects = {o.id: o for o in changed.state_at(round_index, 0.0).objects}
        assert "shelf" in objects and objects["crate_b"].position == (1.55, 1.45)
    def walker_at(round_index: int, t_s: float):
        return {o.id: o for o in transient.state_at(round_index, t_s).objects}.get("walker")

    assert walker_at(2, 9.0) is not None and walker_at(2, 13.0) is None  # scored round 1: 6–12 s
    assert walker_at(3, 9.0) is None and walker_at(3, 17.0) is not None  # scored round 2: 14–20 s
    assert walker_at(5, 3.0) is not None and walker_at(5, 9.0) is None  # scored round 4: 0–6 s
    assert walker_at(6, 9.0) is not None  # scored round 5: the shifts repeat
    # the same crossing, shifted: at the same time into its span the walker is at the same place
    assert walker_at(2, 7.5).position == walker_at(3, 15.5).position == walker_at(5, 1.5).position
    lamp = {lt.id: lt.intensity for lt in transient.state_at(3, 1.0).lights}["lamp"]  # scored round 2: 1–8 s
    assert lamp < {lt.id: lt.intensity for lt in transient.state_at(3, 16.0).lights}["lamp"]


# ---------------------------------------------------------------------------------------------- ray casting


def _box_scene(**extra: object):
    data = _scene(room=None, ambient=1.0, background=[0, 0, 0],
                  objects=[{"id": "b", "position": [2.0, 0.0], "size": [0.2, 0.4, 0.3],
                            "material": {"texture": "flat", "color": [0.5, 0.5, 0.5]}}],
                  camera={"width": 160, "height": 120,
                          "mount": {"pitch_deg": 0, "forward_m": 0, "height_m": 0.15}})
    data.update(extra)
    return parse_scene(data)


def test_box_edges_land_on_the_pixels_the_camera_model_predicts():
    s = _box_scene()
    k = s.camera.intrinsics
    cam = camera_from_pose(0.0, 0.0, 0.0, s.camera.mount, k)
    rgb, depth = RayCastWorld(s).render(cam)
    # Front face x = 1.9 m, y in [-0.2, 0.2], z in [0, 0.3]; camera at z = 0.15 looking along +x, so
    # only the front face is visible.
    corners = np.array([[1.9, 0.2, 0.3], [1.9, -0.2, 0.0]])
    uv, z = cam.project(corners)
    assert np.allclose(z, 1.9)
    u_lo, u_hi = sorted(uv[:, 0])
    v_lo, v_hi = sorted(uv[:, 1])
    uc = np.arange(k.width) + 0.5  # pixel centres
    vc = np.arange(k.height) + 0.5
    inside = ((uc[None, :] > u_lo) & (uc[None, :] < u_hi)) & ((vc[:, None] > v_lo) & (vc[:, None] < v_hi))
    hit = np.isfinite(depth)
    assert hit.sum() > 100
    np.testing.assert_array_equal(hit, inside)
    assert np.allclose(depth[hit], 1.9, atol=1e-5)
    # world +y (left of the robot) is image left (small u); world +z is image up (small v)
    assert uv[0, 0] < k.cx < uv[1, 0] and uv[0, 1] < k.cy < uv[1, 1]
    assert np.allclose(rgb[hit], 0.5, atol=1e-6) and np.all(rgb[~hit] == 0)


def test_floor_depth_back_projects_onto_the_floor_plane_with_a_pitched_camera():
    s = parse_scene(_scene(camera={"width": 96, "height": 72, "mount": {"pitch_deg": 12, "height_m": 0.3}}))
    cam = camera_from_pose(0.5, -0.2, 0.7, s.camera.mount, s.camera.intrinsics)
    _, depth = RayCastWorld(s).render(cam)
    rays = cam.ray_directions_camera() * depth[..., None]  # camera-frame points (z = depth)
    world = rays.reshape(-1, 3) @ cam.camera_to_world[:3, :3].T + cam.center_world
    bottom = world.reshape(72, 96, 3)[-10:]  # lower rows see the floor
    assert np.allclose(bottom[..., 2], 0.0, atol=1e-6)
    uv, _ = cam.project(bottom.reshape(-1, 3))
    expected_u = np.tile(np.arange(96) + 0.5, 10)
    assert np.allclose(uv[:, 0], expected_u, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-180, 180), st.floats(0.1, 0.8),
       st.floats(0.1, 0.8), st.floats(0.1, 0.6), st.floats(-0.6, 0.6))
def test_every_hit_pixel_back_projects_onto_the_yawed_box_surface(x, y, yaw_deg, sx, sy, sz, look):
    s = parse_scene(_scene(room=None, objects=[{"position": [x, y], "size": [sx, sy, sz], "yaw_deg": yaw_deg}],
                           camera={"width": 48, "height": 36}))
    # robot 2.5 m away from the box, facing it (± look rad)
    cam = camera_from_pose(x - 2.5, y, look, s.camera.mount, s.camera.intrinsics)
    _, depth = RayCastWorld(s).render(cam)
    hit = np.isfinite(depth)
    pts = (cam.ray_directions_camera()[hit] * depth[hit][:, None]) @ cam.camera_to_world[:3, :3].T \
        + cam.center_world
    c, si = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    rel = pts - np.array([x, y, sz / 2])
    local = np.stack([c * rel[:, 0] + si * rel[:, 1], -si * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=1)
    ratio = np.max(np.abs(local) / (0.5 * np.array([sx, sy, sz])), axis=1)
    assert np.all(np.abs(ratio - 1.0) < 1e-4), ratio
    # and the box is seen whenever its centre is in the image
    uv, z = cam.project(np.array([[x, y, sz / 2]]))
    if z[0] > 0 and 1 <= uv[0, 0] < 47 and 1 <= uv[0, 1] < 35:
        assert hit[int(uv[0, 1]), int(uv[0, 0])]


def test_screen_space_culling_never_changes_the_image(monkeypatch, small_sandbox):
    from gsrmr_shapes import raycast

    drive = drive_route(small_sandbox.route, 16, 1.8)
    world = RayCastWorld(small_sandbox, 2)
    cams = [camera_from_pose(*p, small_sandbox.camera.mount, small_sandbox.camera.intrinsics) for p in drive.poses]
    culled = [world.render(c, 20.0) for c in cams]

    def whole_image(camera: Camera, corners: np.ndarray, near_m: float = 1e-3) -> np.ndarray:
        out = np.empty((corners.shape[0], 4), np.int64)
        out[:] = (0, camera.width - 1, 0, camera.height - 1)
        return out

    monkeypatch.setattr(raycast, "screen_rects", whole_image)
    for cam, (rgb, depth) in zip(cams, culled, strict=True):
        rgb_all, depth_all = world.render(cam, 20.0)
        assert np.array_equal(rgb, rgb_all) and np.array_equal(depth, depth_all)


def test_directional_light_shadow_darkens_the_floor_behind_a_box():
    data = _scene(ambient=0.3, room={"min": [-5, -5, 0], "max": [5, 5, 3],
                                     "floor": {"texture": "flat", "color": [0.5, 0.5, 0.5]}},
                  lights=[{"type": "directional", "direction": [1, 0, -1], "intensity": 0.7,
                           "shadows": True}],
                  objects=[{"position": [1.5, 0.0], "size": [0.2, 0.6, 0.5]}],
                  camera={"width": 80, "height": 60, "mount": {"pitch_deg": 30, "height_m": 1.5}})
    s = parse_scene(data)
    world = RayCastWorld(s)
    cam = camera_from_pose(3.5, 0.0, math.pi, s.camera.mount, s.camera.intrinsics)  # looking back at it
    rgb, _ = world.render(cam)
    # floor point in the shadow (the light travels along +x, so behind the box) vs a lit one at the side
    shadow_pt, lit_pt = np.array([[1.8, 0.0, 0.0]]), np.array([[1.8, 0.7, 0.0]])
    (us, vs), (ul, vl) = cam.project(shadow_pt)[0][0], cam.project(lit_pt)[0][0]
    dark, lit = rgb[int(vs), int(us)], rgb[int(vl), int(ul)]
    assert np.allclose(dark, 0.5 * 0.3, atol=1e-3)
    assert np.allclose(lit, 0.5 * (0.3 + 0.7 * math.cos(math.radians(45))), atol=1e-3)


def test_textures_are_prefiltered_so_a_fine_checker_far_away_averages_instead_of_aliasing():
    fine = {"texture": "checker", "color": [0.9, 0.9, 0.9], "color2": [0.1, 0.1, 0.1], "scale_m": 0.01}
    s = parse_scene(_scene(ambient=1.0, room={"min": [-50, -50, 0], "max": [50, 50, 30], "floor": fine},
                           camera={"width": 64, "height": 48, "mount": {"pitch_deg": 80, "height_m": 10.0}}))
    rgb, _ = RayCastWorld(s).render(camera_from_pose(0.0, 0.0, 0.0, s.camera.mount, s.camera.intrinsics))
    # 1 cm cells seen from 10 m (≈ 0.3 px each): every pixel is the 50 % mix, not a random cell colour
    assert np.allclose(rgb, 0.5, atol=0.03), (rgb.min(), rgb.max())
    near = parse_scene(_scene(ambient=1.0, room={"min": [-50, -50, 0], "max": [50, 50, 30],
                                                 "floor": {**fine, "scale_m": 0.2}},
                              camera={"width": 64, "height": 48, "mount": {"pitch_deg": 80, "height_m": 0.5}}))
    rgb, _ = RayCastWorld(near).render(camera_from_pose(0.0, 0.0, 0.0, near.camera.mount, near.camera.intrinsics))
    assert rgb.max() > 0.85 and rgb.min() < 0.15  # cells of ≥ 10 px keep their full contrast


# ---------------------------------------------------------------------------------------------- route


def test_sandbox_route_lap_takes_about_29_seconds():
    for name in ("sandbox", "garden"):
        lap = lap_time_s(load_scene(name).route)
        assert lap == pytest.approx(28.8, abs=0.6), (name, lap)


def test_unicycle_step_is_exact_on_a_circle():
    pose = (0.0, 0.0, 0.0)
    for _ in range(100):
        pose = unicycle_step(pose, 0.5, 2 * math.pi / 10.0, 0.1)  # one full turn in 10 s
    assert pose == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    assert unicycle_step((1.0, 2.0, math.pi / 2), 0.3, 0.0, 2.0) == pytest.approx((1.0, 2.6, math.pi / 2))


def test_pure_pursuit_converges_to_the_path_from_an_offset_start():
    route = load_scene("sandbox").route
    path = LoopPath(route.waypoints)
    x, y = path.point_at(0.0)
    drive = drive_route(route, 100, 0.1, pose0=(x + 0.3, y - 0.25, 0.5))
    ends = drive.poses[-10:]
    dense = path.points_at(np.linspace(0, path.length_m, 2000))
    dist = np.min(np.hypot(dense[:, 0][None] - ends[:, 0:1], dense[:, 1][None] - ends[:, 1:2]), axis=1)
    assert np.all(dist < 0.03), dist
    assert np.all(drive.controls[:, 0] <= route.speed_mps + 1e-12)
    v, w, s = PurePursuit().command(path, (x, y, path.heading_at(0.0)), 0.0)
    assert v == pytest.approx(0.3) and abs(w) < 1e-6 and s == pytest.approx(0.0, abs=0.02)


# ---------------------------------------------------------------------------------------------- recorder


@pytest.fixture(scope="module")
def small_sandbox():
    return with_resolution(load_scene("sandbox"), 64, 48)


def test_round_one_writes_a_nerfstudio_dataset_that_reads_back(tmp_path, small_sandbox):
    out = record_round1(small_sandbox, tmp_path / "r1", frames=8)
    frames = read_dataset(out)
    assert len(frames) == 8
    world = RayCastWorld(small_sandbox, 1)
    poses = np.array([f.pose for f in frames])
    assert np.ptp(poses[:, 0]) > 1.0 and np.ptp(poses[:, 1]) > 1.0  # spread over the lap
    for f in frames[::3]:
        cam = camera_from_pose(*f.pose, small_sandbox.camera.mount, small_sandbox.camera.intrinsics)
        assert np.allclose(f.camera.world_to_camera, cam.world_to_camera, atol=1e-9)
        assert f.camera.intrinsics.fx == pytest.approx(cam.intrinsics.fx)
        rgb, depth = world.render(cam)
        assert np.abs(f.image - rgb).max() <= 0.5 / 255 + 1e-6
        assert f.depth_m is not None and np.allclose(f.depth_m, depth, atol=6e-4)


@pytest.fixture(scope="module")
def round2(tmp_path_factory, small_sandbox):
    return Round2Record(record_round2(small_sandbox, tmp_path_factory.mktemp("r2"), seed=3))


def test_round_two_record_has_t_slots_with_virtual_view_and_mask(round2, small_sandbox):
    assert len(round2) == 288 and round2.slot_s == 0.1
    assert np.allclose(round2.times_s, np.arange(288) * 0.1)
    assert round2.server_position_m == small_sandbox.server_position_m
    virtual_slots = 0
    for t in range(0, 288, 8):
        slot = round2[t]
        assert slot.image.shape == (48, 64, 3) and slot.virtual.shape == (48, 64, 3)
        assert slot.mask.shape == (48, 64) and set(np.unique(slot.mask)) <= {0.0, 1.0}
        assert np.all(slot.virtual[slot.mask == 1.0] == 0.0)
        virtual_slots += int((slot.mask == 0).any())
        assert np.allclose(slot.camera.world_to_camera,
                           camera_from_pose(*slot.pose, round2.mount, round2.intrinsics).world_to_camera)
    assert virtual_slots >= 5
    # the start is jittered (seeded) but near the route start
    assert math.dist(round2.poses[0][:2], start_pose(small_sandbox.route)[:2]) < 0.05


def test_round_two_events_change_the_images_at_the_scripted_slots(round2, small_sandbox):
    mapped = RayCastWorld(small_sandbox, 1)  # the world of round 1 at the same poses
    diff = np.zeros(len(round2))
    for t in range(len(round2)):
        slot = round2[t]
        diff[t] = np.abs(slot.image - mapped.render(slot.camera, slot.time_s)[0]).mean()
    times = round2.times_s
    quiet = times < 3.0
    assert diff[quiet].max() < 1.0 / 255  # uint8 quantisation only
    for ev in small_sandbox.events:
        span = (times >= ev.from_s) & (times < min(ev.to_s, ev.from_s + 12.0))
        assert diff[span].max() > 0.01, (ev.type, diff[span].max())
    # bursts: most slots stay close to the mapped world
    assert np.mean(diff < 0.005) > 0.4


# ---------------------------------------------------------------------------------------------- garden, CLI


def test_garden_points_world_renders_with_depth_and_an_occluding_mask():
    s = with_resolution(load_scene("garden"), 96, 72)
    world = make_world(s, 1)
    x, y = LoopPath(s.route.waypoints).point_at(0.0)
    cam = camera_from_pose(x, y, math.pi / 2, s.camera.mount, s.camera.intrinsics)
    rgb, depth = world.render(cam)
    assert np.isfinite(depth).mean() > 0.5 and rgb.std() > 0.05
    _, d = virtual_view(s).render(cam, real_depth_m=depth)
    assert set(np.unique(d)) <= {0.0, 1.0}


def test_point_splatter_puts_each_point_at_its_projected_pixel_with_its_depth(tmp_path):
    pts = np.array([[2.0, 0.3, 0.2], [3.0, -0.5, 0.4], [1.5, 0.0, 0.1]], np.float32)
    cols = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
    np.savez(tmp_path / "pts.npz", means3d=pts, colors=cols)
    s = parse_scene(_scene(room=None, background=[0, 0, 0],
                           points={"path": str(tmp_path / "pts.npz"), "up": [0, 0, 1], "max_radius_px": 0},
                           camera={"width": 64, "height": 48}))
    world = make_world(s, 1)
    cam = camera_from_pose(0.0, 0.0, 0.0, s.camera.mount, s.camera.intrinsics)
    rgb, depth = world.render(cam)
    uv, z = cam.project(pts.astype(np.float64))
    assert np.isfinite(depth).sum() == 3
    for (u, v), zi, col in zip(uv, z, cols, strict=True):
        px = (int(np.floor(v)), int(np.floor(u)))
        assert depth[px] == pytest.approx(zi, rel=1e-5)
        assert np.allclose(rgb[px], col / 255.0)
    # round-2 ambient dimming scales the captured colours
    s2 = parse_scene({**_scene(room=None, background=[0, 0, 0], ambient=1.0,
                               points={"path": str(tmp_path / "pts.npz"), "up": [0, 0, 1], "max_radius_px": 0},
                               camera={"width": 64, "height": 48}),
                      "events": [{"type": "light", "light": "ambient", "from_s": 0.0, "intensity_scale": 0.5}]})
    dim, _ = make_world(s2, 2).render(cam, 1.0)
    assert np.allclose(dim, 0.5 * rgb, atol=1e-6)


def test_cli_records_round_one_and_reports_bad_scenes(tmp_path, capsys):
    assert cli.main(["record", "--scene", "sandbox", "--round", "1", "--out", str(tmp_path / "ds"),
                     "--frames", "3", "--width", "40", "--height", "30", "--quiet"]) == 0
    frames = read_dataset(tmp_path / "ds")
    assert len(frames) == 3 and frames[0].image.shape == (30, 40, 3)
    assert cli.main(["record", "--scene", "no_such_scene", "--round", "1", "--out", str(tmp_path / "x")]) == 2
    assert "no scene named 'no_such_scene'" in capsys.readouterr().err


def test_mount_default_matches_the_documented_camera():
    s = load_scene("sandbox")
    assert s.camera.mount == CameraMount(height_m=0.15, pitch_rad=math.radians(5), forward_m=0.1, left_m=0.0)


# ---------------------------------------------------------------------------------------------- fuzz


def _paths(node: object, prefix: str = "") -> list[tuple[str, list]]:
    """Every (key path, access list) in a YAML tree, key paths spelled like SceneError messages."""
    out: list[tuple[str, list]] = []
    if isinstance(node, dict):
        for k, v in node.items():
            p = f"{prefix}.{k}" if prefix else str(k)
            out.append((p, [k]))
            out += [(q, [k, *acc]) for q, acc in _paths(v, p)]
    elif isinstance(node, list):
        for i, v in enumerate(node):
            p = f"{prefix}[{i}]"
            out.append((p, [i]))
            out += [(q, [i, *acc]) for q, acc in _paths(v, p)]
    return out


SANDBOX_RAW = yaml.safe_load(resolve_scene_path("sandbox").read_text())
JUNK = [None, "x", -1, 0, 1e9, float("nan"), [], {}, [1, 2], True, {"bogus": 1}]


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(_paths(SANDBOX_RAW)), st.sampled_from(JUNK))
def test_any_corrupted_value_in_the_sandbox_is_a_scene_error_or_valid(target, junk):
    path, access = target
    data = copy.deepcopy(SANDBOX_RAW)
    node = data
    for key in access[:-1]:
        node = node[key]
    node[access[-1]] = copy.deepcopy(junk)
    try:
        parse_scene(data)
    except SceneError as exc:
        # the message names a key at or around the corrupted one (never a bare Python error)
        head = str(exc).split(":")[0]
        assert head, str(exc)
        top = path.split(".")[0].split("[")[0]
        assert head.split(".")[0].split("[")[0] in (top, "events"), (path, str(exc))
