"""The robot's scene-change images (gsrmr_robot.scene_change and UplinkCore's use of it): pure, no ROS."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from gsrmr_common.channel import rician_power_samples
from gsrmr_common.link_model import LinkBudget
from gsrmr_robot.scene_change import CHANGE_FADE_QUANTILES, MIN_BASELINE_SCORES, ChangeProbe, SceneChangeDetector
from gsrmr_robot.uplink_core import SlotInputs, UplinkCore

W, H = 320, 240


def _scene(seed: int = 0) -> np.ndarray:
    """A textured panorama wider than the frame (smooth blobs, like a room at thumbnail size), uint8 RGB."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(40, 215, (H // 20, 3 * W // 20, 3))
    return np.kron(coarse, np.ones((20, 20, 1))).astype(np.uint8)


def _walk(detector: SceneChangeDetector, frames: list[np.ndarray], first_stamp: int = 0) -> list[bool]:
    return [detector.update(f, first_stamp + i) for i, f in enumerate(frames)]


def _noisy(frame: np.ndarray, rng: np.random.Generator, sigma: float = 6.0) -> np.ndarray:
    return np.clip(frame + rng.normal(0, sigma, frame.shape), 0, 255).astype(np.uint8)


def test_a_light_switched_on_is_a_change_the_sensor_noise_before_it_is_not():
    rng = np.random.default_rng(1)
    view = _scene()[:, :W]
    frames = [_noisy(view, rng) for _ in range(20)]
    lit = view.astype(np.float32)
    lit[:, : W // 2] *= 1.4  # a lamp lights the left half
    frames += [_noisy(np.clip(lit, 0, 255).astype(np.uint8), rng) for _ in range(5)]
    det = SceneChangeDetector()
    changed = _walk(det, frames)
    assert changed == [False] * 20 + [True] + [False] * 4  # once, in the slot the light came on
    assert det.changes == 1 and det.last_score < det.ratio * det.baseline()


def test_turning_is_no_change_because_the_thumbnails_are_compared_aligned():
    rng = np.random.default_rng(2)
    pano = _scene(3)
    # the camera turns: the view slides 30 px (3 thumbnail pixels, ≈ 6° at a 60° field of view) per slot,
    # after 10 slots of standing still
    offsets = [0] * 10 + [30 * k for k in range(1, 16)]
    frames = [_noisy(pano[:, o:o + W], rng) for o in offsets]
    assert not any(_walk(SceneChangeDetector(), frames))
    # without the alignment the same turn is taken for a change
    assert any(_walk(SceneChangeDetector(max_shift_fraction=0.0), frames))


def test_repeated_frames_are_skipped_and_do_not_empty_the_baseline():
    rng = np.random.default_rng(4)
    view = _scene(5)[:, :W]
    det = SceneChangeDetector()
    stamp = 0
    for _ in range(10):  # a camera at 5 Hz: every frame is seen in two slots
        frame = _noisy(view, rng)
        assert det.update(frame, stamp) is False
        assert det.update(frame, stamp) is False
        stamp += 1
    assert det.baseline() is not None and det.baseline() > 0.0
    # a frame no further from the last than the sensor noise is no change
    assert det.update(_noisy(view, rng), stamp) is False


def test_no_frame_or_another_size_restarts_the_comparison():
    rng = np.random.default_rng(6)
    view = _scene(7)[:, :W]
    det = SceneChangeDetector()
    _walk(det, [_noisy(view, rng) for _ in range(10)])
    assert det.update(None) is False and np.isnan(det.last_score)
    other = np.full((H, W, 3), 255, np.uint8)  # would be a change if compared with the frame before the gap
    assert det.update(other, 100) is False and np.isnan(det.last_score)
    small = np.full((H // 2, W // 2, 3), 0, np.uint8)
    assert det.update(small, 101) is False and np.isnan(det.last_score)


def test_the_first_slots_only_fill_the_baseline():
    det = SceneChangeDetector()
    frames = [np.full((H, W, 3), 30 * k, np.uint8) for k in range(MIN_BASELINE_SCORES + 1)]
    assert not any(_walk(det, frames))  # every frame differs from the one before, but no baseline yet


@pytest.mark.parametrize("kwargs", [{"ratio": 1.0}, {"min_score": -0.1}, {"thumbnail_width_px": 2},
                                   {"window": MIN_BASELINE_SCORES - 1}, {"max_shift_fraction": -0.1},
                                   {"max_shift_fraction": 0.6}])
def test_bad_settings_are_refused(kwargs):
    with pytest.raises(ValueError):
        SceneChangeDetector(**kwargs)


def test_starting_to_drive_raises_the_baseline_instead_of_firing_for_ever():
    rng = np.random.default_rng(10)
    pano = _scene(11)
    still = [_noisy(pano[:, :W], rng, sigma=1.0) for _ in range(30)]  # standing: only the sensor's noise
    # driving: the view slides by a fraction of a thumbnail pixel each slot, a difference no shift removes
    driving = [_noisy(pano[:, 7 * k:7 * k + W], rng) for k in range(1, 40)]
    det = SceneChangeDetector(min_score=0.0, window=30)  # no floor: the baseline alone must adapt
    changed = _walk(det, still + driving)
    assert not any(changed[:30]) and changed[30]  # driving off is a change, to a detector without a floor
    assert not any(changed[30 + 16:])  # within half a window the median is a driving one


# ---------------------------------------------------------------------------------------------- the uplink core
def test_the_fade_a_change_s_image_needs_falls_over_the_wait():
    probe = ChangeProbe(1.0, wait_slots=5)
    fades = rician_power_samples(1.0)
    assert probe.fades[0] == pytest.approx(np.quantile(fades, CHANGE_FADE_QUANTILES[0]))
    assert probe.fades[-1] == pytest.approx(np.quantile(fades, CHANGE_FADE_QUANTILES[1]))
    assert np.all(np.diff(probe.fades) < 0)
    assert not probe.wants_image(10, 1.0, 1.0)  # no change yet
    probe.changed(10)
    assert not probe.wants_image(9, 1.0, 1.0)  # before the change
    assert not probe.wants_image(10, 0.95 * probe.fades[0], 1.0) and probe.wants_image(10, probe.fades[0], 1.0)
    assert probe.wants_image(14, 2e-7 * probe.fades[-1], 2e-7)  # the fades scale with the mean gain
    assert not probe.wants_image(15, 10.0, 1.0)  # the wait is over
    probe.image_sent()
    assert not probe.wants_image(11, 10.0, 1.0)
    with pytest.raises(ValueError):
        ChangeProbe(1.0, wait_slots=0)


def _core(wait: int = 3) -> UplinkCore:
    return UplinkCore(LinkBudget(), 0.1, scene_change=SceneChangeDetector(), change_wait_slots=wait)


def _key_slot(core: UplinkCore, slot: int, frame: np.ndarray, fade: float):
    """A slot whose in-slot rule says key (threshold +inf) at ``fade`` × the mean gain."""
    gain = core.link.mean_gain((0.0, 0.0)) * fade
    return core.run_slot(SlotInputs(slot, frame, slot, (0.0, 0.0, 0.0), (0, 0.01), measured_gain=gain,
                                    gain_threshold=float("inf")))


def _changed_world(slots_before: int = 12):
    rng = np.random.default_rng(8)
    view = _scene(9)[:, :W]
    before = [_noisy(view, rng) for _ in range(slots_before)]
    lit = np.clip(view.astype(np.float32) * 1.5, 0, 255).astype(np.uint8)
    return before, [_noisy(lit, rng) for _ in range(10)]


def test_a_change_sends_an_image_at_the_first_fair_fade():
    core = _core(wait=3)
    before, after = _changed_world()
    good, deep = 1.2 * core.change_probe.fades[0], 0.9 * core.change_probe.fades[-1]
    assert all(_key_slot(core, k, f, good).x == 0 for k, f in enumerate(before))
    slot = len(before)
    changed = _key_slot(core, slot, after[0], deep)
    assert changed.x == 0  # the change, in a deep fade: wait
    assert changed.scene_changed and changed.row.scene_change == 1  # the ledger tells the scheduler where
    sent = _key_slot(core, slot + 1, after[1], good)
    assert sent.x == 1 and sent.jpeg is not None and core.change_images == 1
    assert sent.row.scene_change == 0  # the image of the change is not the change's slot
    assert _key_slot(core, slot + 2, after[2], good).x == 0  # one image per change
    assert core.scene_change.changes == 1


def test_a_change_left_unsent_for_the_wait_is_dropped():
    core = _core(wait=2)
    before, after = _changed_world()
    for k, f in enumerate(before):
        _key_slot(core, k, f, 1.0)
    slot = len(before)
    deep = 0.9 * core.change_probe.fades[-1]
    assert [_key_slot(core, slot + i, after[i], deep).x for i in range(2)] == [0, 0]
    assert _key_slot(core, slot + 2, after[2], 2.0).x == 0 and core.change_images == 0


def test_without_a_detector_or_a_schedule_nothing_changes():
    before, after = _changed_world()
    plain = UplinkCore(LinkBudget(), 0.1)
    assert [_key_slot(plain, k, f, 2.0).x for k, f in enumerate(before + after)] == [0] * (len(before) + 10)
    # no schedule covers the slot: the default upload decides, not the detector
    unscheduled = UplinkCore(LinkBudget(), 0.1, default_upload_image=False, scene_change=SceneChangeDetector())
    rows = [unscheduled.run_slot(SlotInputs(k, f, k, (0.0, 0.0, 0.0), None)) for k, f in enumerate(before + after)]
    assert all(r.x == 0 for r in rows) and unscheduled.scene_change.changes == 1


def test_a_frame_narrower_than_the_thumbnail_is_compared_within_its_own_width():
    """A 6-pixel-wide camera (thumbnail 32 wide, shifts up to 6 px): every shift still overlaps, so no empty
    comparison (a NaN or a warning) decides the score."""
    det = SceneChangeDetector()
    rng = np.random.default_rng(3)
    a = rng.integers(0, 255, (4, 6, 3), np.uint8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        score = det.aligned_difference(det.thumbnail(a), det.thumbnail(255 - a))
    assert math.isfinite(score) and score > 0
