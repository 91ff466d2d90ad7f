"""Headless recording of the paper's two rounds: round 1 as a nerfstudio dataset, round 2 as per-slot records.

Layouts: docs/world.md, "Records" (round 1 through :func:`gsrmr_common.nerfstudio.write_dataset`: camera→world in
OpenGL axes, depth PNG in millimetres). In a round-2 record poses are [a_m, b_m, theta_rad] in ``map``, controls
[v_mps, omega_rps], intrinsics with pixel centres at +0.5, ``depth_mm`` uint16 millimetres (0 = none) and ``mask``
1 = real, 0 = virtual. Pure Python/numpy, no ROS.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace
import json
import math
from pathlib import Path

import numpy as np

from gsrmr_common.camera import Camera, CameraMount, Intrinsics, camera_from_pose
from gsrmr_common.nerfstudio import DatasetFrame, write_dataset
from gsrmr_common.pose2d import Pose2D
from gsrmr_sim.world.kinematics import drive_route, start_pose
from gsrmr_sim.world.points import make_world
from gsrmr_sim.world.scene import Scene
from gsrmr_sim.world.virtual import virtual_view

INDEX_FILE = "index.json"


def with_resolution(scene: Scene, width: int | None = None, height: int | None = None) -> Scene:
    """The scene with its camera rescaled to width×height (same field of view)."""
    if width is None and height is None:
        return scene
    k = scene.camera.intrinsics
    w = int(width) if width is not None else k.width
    h = int(height) if height is not None else k.height
    # keep the horizontal FOV; keep square pixels
    new_k = Intrinsics.from_fov(w, h, 2.0 * math.atan(0.5 * k.width / k.fx))
    return replace(scene, camera=replace(scene.camera, intrinsics=new_k))


def _u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(img) * 255.0), 0, 255).astype(np.uint8)


def record_round1(scene: Scene, out_dir: str | Path, frames: int | None = None, seed: int = 0,
                  progress: bool = False) -> Path:
    """Write H = ``frames`` (default ``scene.frames``) mapping frames as a nerfstudio dataset.

    Returns the dataset directory.
    """
    out = Path(out_dir)
    h = int(frames or scene.frames)
    duration_s = scene.slots * scene.slot_s
    drive = drive_route(scene.route, h, duration_s / h, pose0=start_pose(scene.route))
    world = make_world(scene, 1)
    cam_k, mount = scene.camera.intrinsics, scene.camera.mount
    ds: list[DatasetFrame] = []
    for i, (t_s, pose) in enumerate(zip(drive.times_s, drive.poses, strict=True)):
        cam = camera_from_pose(*pose, mount, cam_k)
        rgb, depth = world.render(cam, float(t_s))
        ds.append(DatasetFrame(cam, rgb, depth, (float(pose[0]), float(pose[1]), float(pose[2]))))
        if progress and i % 20 == 0:
            print(f"round 1: frame {i}/{h}", flush=True)
    write_dataset(out, ds)
    (out / "gsrmr_world.json").write_text(json.dumps(
        {"scene": scene.name, "scene_file": scene.source, "round": 1, "seed": seed, "frames": h,
         "lap_duration_s": duration_s, "mount": _mount_dict(mount)}, indent=1))
    return out


def _mount_dict(m: CameraMount) -> dict:
    return m.as_parameters(prefix="")


def record_round2(scene: Scene, out_dir: str | Path, slots: int | None = None, seed: int = 0,
                  progress: bool = False, round_index: int = 2) -> Path:
    """Write T = ``slots`` (default ``scene.slots``) operating slots with r_t, s_t, v_t, d_t.

    ``round_index`` picks the world: 2 (default) is the operating round with its change events; 1 is the
    mapping round's world (what the robot saw when the model was built) at the same slot poses.

    Returns the record directory.
    """
    out = Path(out_dir)
    (out / "slots").mkdir(parents=True, exist_ok=True)
    t_slots = int(slots or scene.slots)
    pose0 = start_pose(scene.route, scene.route.start_jitter_m, seed)
    drive = drive_route(scene.route, t_slots, scene.slot_s, pose0=pose0)
    world = make_world(scene, round_index)
    virtual = virtual_view(scene)
    k, mount = scene.camera.intrinsics, scene.camera.mount
    entries = []
    for t in range(t_slots):
        t_s = float(drive.times_s[t])
        pose = tuple(float(v) for v in drive.poses[t])
        cam = camera_from_pose(*pose, mount, k)
        rgb, depth = world.render(cam, t_s)
        v, d = virtual.render(cam, time_s=t_s, real_depth_m=depth)
        rel = f"slots/slot_{t:05d}.npz"
        depth_mm = np.clip(np.round(np.nan_to_num(depth, posinf=0.0) * 1000.0), 0, 65535).astype(np.uint16)
        np.savez_compressed(out / rel, image=_u8(rgb), depth_mm=depth_mm, virtual=_u8(v),
                            mask=(d > 0.5).astype(np.uint8))
        entries.append({"t": t, "time_s": t_s, "pose": list(pose),
                        "control": [float(c) for c in drive.controls[t]],
                        "events": [i for i, ev in enumerate(scene.events) if ev.active(t_s, max(1, round_index - 1))],
                        "file": rel})
        if progress and t % 20 == 0:
            print(f"round 2: slot {t}/{t_slots}", flush=True)
    index = {"format": "gsrmr-round2/1", "scene": scene.name, "scene_file": scene.source, "round": 2,
             "seed": seed, "slot_s": scene.slot_s, "slots": t_slots,
             "intrinsics": {"fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": k.width, "h": k.height},
             "mount": _mount_dict(mount), "server_position_m": list(scene.server_position_m),
             "events": [{"type": ev.type, "from_s": ev.from_s,
                         "to_s": ev.to_s if math.isfinite(ev.to_s) else None,
                         "target": ev.target or (ev.shape.id if ev.shape else "")} for ev in scene.events],
             "frames": entries}
    (out / INDEX_FILE).write_text(json.dumps(index, indent=1))
    return out


@dataclass
class SlotRecord:
    """One operating slot: r_t (float32 RGB [0, 1]), depth (m), s_t, v_t (float32), d_t (float32 {0, 1})."""

    t: int
    time_s: float
    pose: Pose2D
    camera: Camera
    image: np.ndarray
    depth_m: np.ndarray
    virtual: np.ndarray
    mask: np.ndarray
    events: list[int]


class Round2Record:
    """Reader of a round-2 record directory (see the module docstring for the layout)."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        path = self.root / INDEX_FILE
        if not path.exists():
            raise FileNotFoundError(f"no {INDEX_FILE} in {self.root}")
        self.index = json.loads(path.read_text())
        if self.index.get("format") != "gsrmr-round2/1":
            raise ValueError(f"{path}: not a gsrmr round-2 record")
        ki = self.index["intrinsics"]
        self.intrinsics = Intrinsics(ki["fl_x"], ki["fl_y"], ki["cx"], ki["cy"], ki["w"], ki["h"])
        self.mount = CameraMount(**self.index["mount"])
        self.slot_s = float(self.index["slot_s"])
        self.server_position_m = tuple(self.index["server_position_m"])

    def __len__(self) -> int:
        return len(self.index["frames"])

    @property
    def poses(self) -> np.ndarray:
        """T×3 robot poses (a_m, b_m, theta_rad) in the map frame."""
        return np.array([f["pose"] for f in self.index["frames"]], dtype=np.float64).reshape(-1, 3)

    @property
    def times_s(self) -> np.ndarray:
        """T slot start times (s since the round start)."""
        return np.array([f["time_s"] for f in self.index["frames"]], dtype=np.float64)

    def camera(self, t: int) -> Camera:
        """The camera of slot t."""
        return camera_from_pose(*self.index["frames"][t]["pose"], self.mount, self.intrinsics)

    def __getitem__(self, t: int) -> SlotRecord:
        if not -len(self) <= t < len(self):
            raise IndexError(f"slot {t} out of range 0..{len(self) - 1}")
        entry = self.index["frames"][t]
        with np.load(self.root / entry["file"]) as z:
            image = z["image"].astype(np.float32) / 255.0
            virtual = z["virtual"].astype(np.float32) / 255.0
            mask = z["mask"].astype(np.float32)
            depth_mm = z["depth_mm"]
        depth = np.where(depth_mm > 0, depth_mm.astype(np.float32) * 1e-3, np.inf).astype(np.float32)
        return SlotRecord(int(entry["t"]), float(entry["time_s"]), tuple(entry["pose"]),  # type: ignore[arg-type]
                          self.camera(t), image, depth, virtual, mask, list(entry["events"]))

    def __iter__(self) -> Iterator[SlotRecord]:
        for t in range(len(self)):
            yield self[t]
