"""nerfstudio ``transforms.json`` datasets: the one reader and writer of the format in gsrmr.

The world recorder writes round-1 frames with :func:`write_dataset`, ``gsrmr-dataset`` streams them with
:class:`DatasetWriter`, the GS trainer reads them with :func:`read_dataset`. The folder layout and the fields:
docs/dataset_tool.md, "Output". Units and axes: intrinsics in pixels with pixel centres at +0.5 (COLMAP/nerfstudio);
``transform_matrix`` camera→world in OpenGL/Blender axes (x right, y up, z back), metres in ``map`` for a gsrmr
dataset; frames may carry their own intrinsics; ``gsrmr_pose`` = [a_m, b_m, theta_rad]; a sparse point cloud is named
by ``ply_file_path`` (:func:`dataset_point_cloud`, :meth:`DatasetWriter.set_point_cloud`).
"""

from __future__ import annotations

from dataclasses import dataclass
import json
import math
from pathlib import Path

import cv2
import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from gsrmr_common.camera import Camera, Intrinsics, opencv_w2c_to_opengl_c2w, opengl_c2w_to_opencv_w2c
from gsrmr_common.pose2d import Pose2D

DEPTH_SCALE_M = 1e-3  # depth PNG unit: millimetres
POINT_CLOUD_KEY = "ply_file_path"  # nerfstudio: the sparse point cloud, relative to the dataset folder
POINT_CLOUD_FILE = "sparse_pc.ply"  # the name nerfstudio's COLMAP export gives it


@dataclass
class DatasetFrame:
    """One training view: OpenCV camera, RGB float32 image in [0, 1] (H×W×3), optional depth [m]."""

    camera: Camera
    image: np.ndarray
    depth_m: np.ndarray | None = None
    pose: Pose2D | None = None  # robot (a_m, b_m, theta_rad) if known
    file_path: str = ""


def _intrinsics_dict(k: Intrinsics) -> dict:
    return {"fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": k.width, "h": k.height}


class DatasetWriter:
    """Writes a nerfstudio dataset frame by frame: each image (and depth) goes to disk as it is added, the
    ``transforms.json`` at :meth:`finish` — so a long recording never has to be held in memory.

    ``add(frame, index)`` names the files ``frame_<index>`` (default: the next number); :meth:`finish` lists the
    frames by index (they must be 0 … n − 1, each once) with the intrinsics of frame 0 as the shared ones (a
    frame with other intrinsics carries its own keys). Output is deterministic: same frames, same bytes.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        (self.root / "images").mkdir(parents=True, exist_ok=True)
        self._entries: dict[int, tuple[Intrinsics, dict]] = {}
        self._point_cloud: str | None = None

    def set_point_cloud(self, points_m: np.ndarray, colors: np.ndarray, name: str = POINT_CLOUD_FILE) -> str:
        """Write a sparse point cloud (N×3 points in the poses' frame, N×3 colours: ``uint8`` or float in [0, 1])
        as ``name`` under the root and name it in ``transforms.json`` (``ply_file_path``); returns ``name``."""
        write_point_cloud(self.root / name, points_m, colors)
        self._point_cloud = name
        return name

    def add(self, frame: DatasetFrame, index: int | None = None) -> str:
        """Write one frame's image (RGB, ``uint8`` as it is or float in [0, 1]) and depth; returns its
        ``file_path`` (relative to the root)."""
        i = len(self._entries) if index is None else int(index)
        if i < 0 or i in self._entries:
            raise ValueError(f"frame {i}: index already written or negative")
        img = np.asarray(frame.image)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"frame {i}: image must be H×W×3, got {img.shape}")
        if (img.shape[1], img.shape[0]) != (frame.camera.width, frame.camera.height):
            raise ValueError(f"frame {i}: image {img.shape[1]}×{img.shape[0]} does not match its camera "
                             f"{frame.camera.width}×{frame.camera.height}")
        rel = f"images/frame_{i:05d}.png"
        u8 = img if img.dtype == np.uint8 else np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
        cv2.imwrite(str(self.root / rel), cv2.cvtColor(u8, cv2.COLOR_RGB2BGR))
        entry: dict = {"file_path": rel,
                       "transform_matrix": opencv_w2c_to_opengl_c2w(frame.camera.world_to_camera).tolist()}
        if frame.depth_m is not None:
            (self.root / "depths").mkdir(exist_ok=True)
            drel = f"depths/frame_{i:05d}.png"
            depth = np.nan_to_num(np.asarray(frame.depth_m, dtype=np.float64), nan=0.0, posinf=0.0)
            mm = np.clip(np.round(depth / DEPTH_SCALE_M), 0, 65535).astype(np.uint16)
            cv2.imwrite(str(self.root / drel), mm)
            entry["depth_file_path"] = drel
        if frame.pose is not None:
            entry["gsrmr_pose"] = [float(v) for v in frame.pose]
        self._entries[i] = (frame.camera.intrinsics, entry)
        return rel

    def finish(self) -> Path:
        """Write ``transforms.json`` of the frames added; returns its path."""
        if not self._entries:
            raise ValueError("write_dataset: no frames")
        if sorted(self._entries) != list(range(len(self._entries))):
            missing = sorted(set(range(max(self._entries) + 1)) - set(self._entries))
            raise ValueError(f"frames must be numbered 0 … n − 1; missing {missing[:5]}")
        shared = self._entries[0][0]
        meta: dict = {"camera_model": "OPENCV", **_intrinsics_dict(shared),
                      "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": []}
        for i in range(len(self._entries)):
            intrinsics, entry = self._entries[i]
            entry = dict(entry)
            if intrinsics != shared:
                head = {k: entry.pop(k) for k in ("file_path", "transform_matrix")}
                entry = {**head, **_intrinsics_dict(intrinsics), **entry}
            meta["frames"].append(entry)
        if any("depth_file_path" in f for f in meta["frames"]):
            meta["depth_unit_scale_factor"] = DEPTH_SCALE_M
        if self._point_cloud is not None:
            meta[POINT_CLOUD_KEY] = self._point_cloud
        out = self.root / "transforms.json"
        out.write_text(json.dumps(meta, indent=1))
        return out


def write_dataset(root: str | Path, frames: list[DatasetFrame],
                  point_cloud: tuple[np.ndarray, np.ndarray] | None = None) -> Path:
    """Write frames as a nerfstudio dataset under ``root``; returns the transforms.json path. ``point_cloud``
    (points N×3 in the poses' frame, colours N×3) is written as ``sparse_pc.ply`` and named by ``ply_file_path``."""
    writer = DatasetWriter(root)
    if not frames:
        raise ValueError("write_dataset: no frames")
    for frame in frames:
        writer.add(frame)
    if point_cloud is not None:
        writer.set_point_cloud(*point_cloud)
    return writer.finish()


def write_point_cloud(path: str | Path, points_m: np.ndarray, colors: np.ndarray) -> Path:
    """A point cloud as nerfstudio's COLMAP export writes it: binary ``.ply``, one ``vertex`` element of float32
    ``x y z`` and uint8 ``red green blue`` (``colors`` N×3: ``uint8``, or float in [0, 1], rounded)."""
    pts = np.asarray(points_m, dtype=np.float64)
    col = np.asarray(colors)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ValueError(f"point cloud: points must be a finite N×3 array, got shape {pts.shape}")
    if col.shape != pts.shape:
        raise ValueError(f"point cloud: colours must be N×3 like the points, got {col.shape} for {pts.shape}")
    u8 = col if col.dtype == np.uint8 else np.clip(np.round(col.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    data = np.empty(len(pts), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                     ("blue", "u1")])
    for i, axis in enumerate("xyz"):
        data[axis] = pts[:, i]
    for i, channel in enumerate(("red", "green", "blue")):
        data[channel] = u8[:, i]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))
    return path


def read_point_cloud(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(N×3 float64 points, N×3 float64 colours in [0, 1]) of a ``.ply`` point cloud: ``vertex`` ``x y z`` and
    ``red green blue`` (integer 0–255, or float in [0, 1]; mid grey 0.5 when the file has no colour). ValueError
    naming the file for anything else."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no point cloud at {path}")
    try:
        ply = PlyData.read(str(path))
    except (PlyParseError, ValueError, EOFError, IndexError, TypeError) as exc:
        raise ValueError(f"{path}: not a readable .ply file ({exc})") from exc
    if "vertex" not in [e.name for e in ply.elements]:
        raise ValueError(f"{path}: no 'vertex' element")
    v = ply["vertex"].data
    fields = set(v.dtype.names or ())
    if not {"x", "y", "z"} <= fields:
        raise ValueError(f"{path}: vertex needs x, y, z properties, has {sorted(fields)}")
    points = np.stack([np.asarray(v[a], dtype=np.float64) for a in "xyz"], axis=1)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        raise ValueError(f"{path}: a point holds NaN/inf (first at vertex {int(np.argmin(finite))})")
    channels = ("red", "green", "blue")
    if set(channels) <= fields:
        raw = np.stack([np.asarray(v[c]) for c in channels], axis=1)
        colors = raw.astype(np.float64) / 255.0 if np.issubdtype(raw.dtype, np.integer) else raw.astype(np.float64)
    else:
        colors = np.full_like(points, 0.5)
    return points, np.clip(colors, 0.0, 1.0)


def transforms_path(root: str | Path) -> Path:
    """The ``transforms.json`` of a dataset given as its folder or the file itself."""
    root = Path(root)
    return root if root.is_file() else root / "transforms.json"


def dataset_point_cloud(root: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The point cloud the dataset names (``ply_file_path`` in transforms.json, relative to the dataset folder):
    (N×3 points [m, the poses' frame], N×3 colours in [0, 1]), or None when it names none."""
    path = transforms_path(root)
    if not path.exists():
        raise FileNotFoundError(f"no transforms.json at {path}")
    rel = json.loads(path.read_text()).get(POINT_CLOUD_KEY)
    if rel is None:
        return None
    if not isinstance(rel, str) or not rel:
        raise ValueError(f"{path}: {POINT_CLOUD_KEY!r} must be a path relative to the dataset folder")
    return read_point_cloud(path.parent / rel)


def _frame_intrinsics(meta: dict, entry: dict, name: str) -> Intrinsics:
    keys = ("fl_x", "fl_y", "cx", "cy", "w", "h")
    values = {}
    for key in keys:
        value = entry.get(key, meta.get(key))
        if value is None:
            raise ValueError(f"{name}: missing intrinsics key {key!r}")
        if not isinstance(value, int | float) or not math.isfinite(value):
            raise ValueError(f"{name}: intrinsics key {key!r} is not a finite number")
        values[key] = value
    return Intrinsics(float(values["fl_x"]), float(values["fl_y"]), float(values["cx"]), float(values["cy"]),
                      int(values["w"]), int(values["h"]))


def read_dataset(root: str | Path, *, load_images: bool = True) -> list[DatasetFrame]:
    """Read a nerfstudio dataset (``root`` is the folder or its transforms.json).

    Images are returned as float32 RGB in [0, 1]; depth in metres when present. Images whose size
    differs from the stated w×h are rejected with a clear error.
    """
    root = Path(root)
    path = root if root.is_file() else root / "transforms.json"
    if not path.exists():
        raise FileNotFoundError(f"no transforms.json at {path}")
    meta = json.loads(path.read_text())
    base = path.parent
    frames_meta = meta.get("frames")
    if not isinstance(frames_meta, list) or not frames_meta:
        raise ValueError(f"{path}: 'frames' must be a non-empty list")
    depth_scale = float(meta.get("depth_unit_scale_factor", DEPTH_SCALE_M))
    out: list[DatasetFrame] = []
    for i, entry in enumerate(frames_meta):
        name = f"{path}: frame {i}"
        if "file_path" not in entry or "transform_matrix" not in entry:
            raise ValueError(f"{name}: needs 'file_path' and 'transform_matrix'")
        c2w = np.asarray(entry["transform_matrix"], dtype=np.float64)
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise ValueError(f"{name}: transform_matrix must be a finite 4×4 (or 3×4)")
        k = _frame_intrinsics(meta, entry, name)
        camera = Camera(k, opengl_c2w_to_opencv_w2c(c2w))
        image = np.zeros((0, 0, 3), np.float32)
        depth = None
        if load_images:
            img_path = base / entry["file_path"]
            bgr = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ValueError(f"{name}: cannot read image {img_path}")
            if bgr.shape[:2] != (k.height, k.width):
                raise ValueError(f"{name}: image is {bgr.shape[1]}×{bgr.shape[0]}, transforms.json says "
                                 f"{k.width}×{k.height}")
            image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
            if "depth_file_path" in entry:
                raw = cv2.imread(str(base / entry["depth_file_path"]), cv2.IMREAD_UNCHANGED)
                if raw is None:
                    raise ValueError(f"{name}: cannot read depth {entry['depth_file_path']}")
                depth = raw.astype(np.float32) * depth_scale
        pose = entry.get("gsrmr_pose")
        out.append(DatasetFrame(camera, image, depth, tuple(pose) if pose else None, entry["file_path"]))
    return out


def holdout_split(frames: list[DatasetFrame], every: int) -> tuple[list[DatasetFrame], list[DatasetFrame]]:
    """(training, held-out) frames: every ``every``-th frame (the last of each group of ``every``) is held
    out; ``every`` ≤ 0 holds out none. The split of ``gsrmr-train --holdout-every``, ``gsrmr-compact`` and
    ``gsrmr-survey`` (which scores the held-out frames only)."""
    if every <= 0:
        return list(frames), []
    return ([f for i, f in enumerate(frames) if i % every != every - 1],
            [f for i, f in enumerate(frames) if i % every == every - 1])
