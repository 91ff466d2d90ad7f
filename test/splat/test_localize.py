"""The registration engine (gsrmr_splat.localize): a render of the model itself is found from a moved guess, and
what cannot be trusted is refused."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from gsrmr_common.camera import Camera
from gsrmr_sim.shared_data import garden_model, load_garden
from gsrmr_splat.localize import FEW_MATCHES, TOO_FAR, LocalizeConfig, register
from gsrmr_splat.render import render


@pytest.fixture(scope="module")
def garden():
    model = garden_model()
    _, _, cams = load_garden()
    small = [Camera(c.intrinsics.scaled(324, 210), c.world_to_camera) for c in cams]
    return model, small


def moved(camera: Camera, shift_m, turn_rad) -> Camera:
    c2w = camera.camera_to_world.copy()
    c2w[:3, 3] += shift_m
    c2w[:3, :3] = cv2.Rodrigues(np.asarray(turn_rad, np.float64))[0] @ c2w[:3, :3]
    return Camera(camera.intrinsics, np.linalg.inv(c2w))


def errors(a: Camera, b: Camera) -> tuple[float, float]:
    r = a.world_to_camera[:3, :3] @ b.world_to_camera[:3, :3].T
    return (float(np.linalg.norm(a.camera_to_world[:3, 3] - b.camera_to_world[:3, 3])),
            math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(r) - 1) / 2)))))


def test_a_render_is_found_from_a_guess_5_cm_and_2_degrees_off(garden):
    model, cams = garden
    for cam in cams:
        image = render(model, cam).rgb
        guess = moved(cam, [0.03, -0.03, 0.025], [0.0, 0.02, 0.025])
        reg = register(model, image, guess)
        assert reg.accepted, reg.refused
        err_m, err_deg = errors(reg.camera, cam)
        assert err_m < 0.002 and err_deg < 0.05, (err_m, err_deg)
        assert reg.loss_after < reg.loss_before and reg.inliers >= 20
        assert reg.correction_m == pytest.approx(errors(guess, cam)[0], rel=0.1)


def test_what_cannot_be_trusted_is_refused_and_keeps_the_guess(garden):
    model, cams = garden
    cam = cams[0]
    flat = np.full((cam.height, cam.width, 3), 0.5, np.float32)  # nothing to track
    reg = register(model, flat, cam)
    assert not reg.accepted and reg.refused == FEW_MATCHES and reg.camera is cam
    image = render(model, cam).rgb
    tight = LocalizeConfig(max_correction_m=0.01)  # a correction larger than any drift is refused
    reg = register(model, image, moved(cam, [0.05, 0.0, 0.0], [0.0, 0.0, 0.0]), config=tight)
    assert not reg.accepted and reg.refused == TOO_FAR
    with pytest.raises(ValueError):
        register(model, image[:-1], cam)
