"""The server's MR content (gsrmr_server.mr): agent files, the virtual view, the mask and m = d·r + (1 − d)·v.

The virtual view is occluded by whatever real depth it is given: the simulator's ray-cast depth here
(the world is the only one that knows it), the GS render's depth on the live server.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from gsrmr_common.camera import CameraMount, Intrinsics, camera_from_pose
from gsrmr_server.mr.blend import compose_mask, mr_image
from gsrmr_server.mr.content import (
    AgentsView,
    MRContentError,
    agent_pose,
    load_mr_content,
    parse_mr_content,
    resolve_mr_content_path,
)
from gsrmr_sim.world.raycast import RayCastWorld
from gsrmr_sim.world.scene import load_scene, parse_scene

MOUNT = CameraMount(height_m=0.15, pitch_rad=0.0, forward_m=0.0)
K = Intrinsics.from_fov(160, 120, math.radians(70))


def _ghost(x_m: float) -> AgentsView:
    """A red cylinder at (x_m, 0), lit only by ambient 1.0 (so its colour is its albedo)."""
    return AgentsView(parse_mr_content({"ambient": 1.0, "virtual_agents": [
        {"id": "ghost", "shape": "cylinder", "position": [x_m, 0.0], "radius_m": 0.1, "height_m": 0.2,
         "material": {"texture": "flat", "color": [1, 0, 0]}}]}))


def _box_world() -> RayCastWorld:
    return RayCastWorld(parse_scene({
        "room": None, "ambient": 1.0, "background": [0, 0, 0], "route": {"waypoints": [[0, 0], [1, 0], [1, 1]]},
        "objects": [{"id": "b", "position": [2.0, 0.0], "size": [0.2, 0.4, 0.3],
                     "material": {"texture": "flat", "color": [0.5, 0.5, 0.5]}}],
        "camera": {"width": K.width, "height": K.height, "hfov_deg": 70,
                   "mount": {"pitch_deg": 0, "forward_m": 0, "height_m": 0.15}}}))


def test_virtual_agent_behind_a_real_box_is_hidden_and_in_front_is_shown():
    world = _box_world()
    cam = camera_from_pose(0.0, 0.0, 0.0, MOUNT, K)
    real, depth = world.render(cam)
    for agent_x, expect_visible in ((3.0, False), (1.0, True)):
        v, d = _ghost(agent_x).render(cam, real_depth_m=depth)
        assert set(np.unique(d)) <= {0.0, 1.0} and d.dtype == np.float32 and v.dtype == np.float32
        assert np.all(v[d == 1.0] == 0.0)
        virtual_px = d == 0.0
        if expect_visible:
            assert virtual_px.sum() > 20
            assert np.allclose(v[virtual_px], [1.0, 0.0, 0.0])
            m = mr_image(real, v, d)
            assert np.allclose(m[virtual_px], [1.0, 0.0, 0.0])
            assert np.allclose(m[~virtual_px], real[~virtual_px])
        else:
            assert virtual_px.sum() == 0
    # the hidden agent is really in view (only occluded): with no real depth it shows
    assert (_ghost(3.0).render(cam)[1] == 0).sum() > 0


def test_mask_treats_missing_real_depth_as_no_surface():
    virtual = np.array([[1.0, 1.0, 1.0, np.inf]], np.float32)
    real = np.array([[0.0, np.nan, 0.5, 0.5]], np.float32)
    assert compose_mask(virtual, real).tolist() == [[0.0, 0.0, 1.0, 1.0]]


def test_moving_agent_goes_there_and_back():
    walker = next(a for a in load_mr_content("sandbox").agents if a.path is not None)
    x0, y0, _ = agent_pose(walker, 0.0)
    x1, _, yaw1 = agent_pose(walker, 1.4 / 0.2)  # end of the 1.4 m segment
    x2, _, yaw2 = agent_pose(walker, 2 * 1.4 / 0.2)
    assert (x0, y0) == pytest.approx((-0.7, 0.55)) and x1 == pytest.approx(0.7) and x2 == pytest.approx(-0.7)
    assert math.cos(yaw2 - yaw1) < 0


def test_shipped_mr_content_matches_its_scene():
    """Each shipped scene names its MR content; the agents are lit by a copy of the scene's round-1 lights."""
    for name in ("sandbox", "garden"):
        scene, content = load_scene(name), load_mr_content(name)
        assert scene.mr_content == name and resolve_mr_content_path(name).name == f"{name}.yaml"
        assert len(content.agents) == 2 and any(a.path is not None for a in content.agents)
        assert content.lighting.lights == scene.lights and content.lighting.ambient == scene.ambient


@pytest.mark.parametrize(("data", "message"), [
    ({"virtual_agents": [{"position": [0, 0], "colour": 1}]}, r"virtual_agents\[0\]\.colour: unknown key"),
    ({"virtual_agents": [{"position": [0, 0], "path": {"waypoints": [[0, 0]]}}]},
     r"virtual_agents\[0\]\.path\.waypoints: needs at least 2"),
    ({"virtual_agents": [{"id": "a", "position": [0, 0]}, {"id": "a", "position": [1, 0]}]},
     r"virtual_agents\[1\]\.id: duplicate id 'a'"),
    ({"ambient": -1}, r"ambient: must be ≥ 0"),
    ({"objects": []}, r"objects: unknown key"),
])
def test_mr_content_errors_name_the_key(data, message):
    with pytest.raises(MRContentError, match=message):
        parse_mr_content(data)


def test_mr_content_file_errors_carry_the_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"virtual_agents": [{"position": [0, 0], "path": {"loop": 1,
                                                                                     "waypoints": [[0, 0], [1, 0]]}}]}))
    with pytest.raises(MRContentError, match=r"bad\.yaml: virtual_agents\[0\]\.path\.loop: must be true or false"):
        load_mr_content(str(bad))
    with pytest.raises(FileNotFoundError, match="no MR content named 'nowhere'"):
        load_mr_content("nowhere")


def test_empty_content_shows_the_real_image_everywhere():
    cam = camera_from_pose(0.0, 0.0, 0.0, MOUNT, K)
    v, d = AgentsView(parse_mr_content({})).render(cam)
    assert np.all(d == 1.0) and np.all(v == 0.0)
    with pytest.raises(ValueError, match="real depth"):
        _ghost(1.0).render(cam, real_depth_m=np.zeros((2, 2), np.float32))


class _RenderOnly:
    """A virtual-view source with only ``render`` (the VirtualViewSource protocol): composed in sequence."""

    def __init__(self, view: AgentsView) -> None:
        self.view = view

    def render(self, camera, *, time_s=0.0, real_depth_m=None):
        return self.view.render(camera, time_s=time_s, real_depth_m=real_depth_m)


def test_the_composer_casts_the_virtual_view_beside_the_render_and_gets_the_sequential_result():
    """MRComposer starts AgentsView.cast on a worker thread before the GS render and occludes it by the render's
    depth afterwards: every slot's MR image, mask, virtual view and loss equal those of the one-thread path."""
    from gsrmr_common.jpeg import encode_jpeg
    from gsrmr_common.wire import PoseKey
    from gsrmr_server.compose import MRComposer
    from gsrmr_server.uplink import SlotUploads
    from gsrmr_splat.model import GaussianModel

    rng = np.random.default_rng(3)
    model = GaussianModel.from_points(rng.uniform([0.5, -1, 0], [3, 1, 0.5], (800, 3)), rng.uniform(0, 1, (800, 3)),
                                      scales_m=0.05, opacities=0.8)
    view = AgentsView(parse_mr_content({"ambient": 1.0, "virtual_agents": [
        {"id": "ghost", "shape": "cylinder", "position": [1.0, 0.0], "radius_m": 0.1,
         "path": {"waypoints": [[1.0, -0.3], [1.0, 0.3]], "speed_mps": 0.5},
         "height_m": 0.3, "material": {"texture": "flat", "color": [1, 0, 0]}}]}))
    overlapped = MRComposer(model, view, K, MOUNT, (0.2, 0.2, 0.2), render_threads=1)
    sequential = MRComposer(model, _RenderOnly(view), K, MOUNT, (0.2, 0.2, 0.2), render_threads=1)
    jpeg = encode_jpeg(rng.integers(0, 255, (K.height, K.width, 3), np.uint8), 90)
    shown = 0
    for slot in range(6):
        uploads = SlotUploads(slot, key=PoseKey(slot, -0.2 * slot, 0.05 * slot, 0.02 * slot),
                              jpeg=jpeg if slot % 2 else None)
        a = overlapped.compose(uploads, None, 0.4 * slot)
        b = sequential.compose(uploads, None, 0.4 * slot)
        for got, want in ((a.mr, b.mr), (a.mask, b.mask), (a.virtual, b.virtual), (a.gs_mr, b.gs_mr)):
            np.testing.assert_array_equal(got, want)
        assert (a.source, a.gs_loss) == (b.source, b.gs_loss)
        shown += int((a.mask == 0).sum() > 0)
    assert overlapped._caster is not None and sequential._caster is None
    assert shown >= 3  # the agent was in view (not everywhere occluded): the test compares something
