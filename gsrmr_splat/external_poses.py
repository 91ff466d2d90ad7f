"""Camera poses of the images a model was trained on, read from nerfstudio, COLMAP and 3DGS files and from gsrmr's own
datasets (:func:`detect_format` picks the reader). Every reader returns ``{key: 4×4 camera→world}`` with OpenCV camera
axes (x right, y down, z forward), in the frame and units of the file's model, keyed by :func:`image_key`. Formats and
pairing: docs/splatting.md, "Aligning a model trained elsewhere".
"""

from __future__ import annotations

from collections.abc import Iterable
import json
import math
from pathlib import Path, PurePosixPath, PureWindowsPath
import re

import numpy as np
from scipy.spatial.transform import Rotation

from gsrmr_common.camera import opengl_c2w_to_opencv_w2c
from gsrmr_common.nerfstudio import read_dataset

IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".exr", ".webp", ".ppm", ".pgm",
                              ".heic", ".cr2", ".dng"})
# nerfstudio's value of ``applied_transform`` for datasets converted from COLMAP before the key existed
# (nerfstudio_dataparser.py uses it when transforms.json lacks the key and DIR/colmap/sparse/0 exists).
NERFSTUDIO_LEGACY_APPLIED_TRANSFORM = ((0.0, 1.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -1.0, 0.0))
ROTATION_TOL = 1e-4
_TRAILING_NUMBER = re.compile(r"^(.*?)(\d+)$")


class PoseFileError(ValueError):
    """A camera-pose file that cannot be read; the message names the file and what is wrong."""


def image_key(name: str) -> str:
    """The matching key of an image name: its base name (after the last ``/`` or ``\\``) without a final image
    extension (:data:`IMAGE_EXTENSIONS`, any case). Other dots stay: ``frame.0001`` keeps its ``.0001``."""
    base = PureWindowsPath(PurePosixPath(str(name)).name).name
    stem, dot, ext = base.rpartition(".")
    return stem if dot and stem and f".{ext.lower()}" in IMAGE_EXTENSIONS else base


def shift_frame_numbers(poses: dict[str, np.ndarray], offset: int) -> dict[str, np.ndarray]:
    """The same poses with ``offset`` added to the trailing number of every key, keeping its zero padding
    (``frame_00001`` with offset −1 → ``frame_00000``); keys without a trailing number are kept as they are.

    ns-process-data renumbers the images it copies from ``frame_00001`` in sorted order, while gsrmr datasets
    count from ``frame_00000``: a model processed from a gsrmr dataset's images pairs with offset −1.
    """
    out: dict[str, np.ndarray] = {}
    for key, pose in poses.items():
        match = _TRAILING_NUMBER.match(key)
        new = key
        if match and offset:
            number = int(match.group(2)) + offset
            if number < 0:
                continue
            new = f"{match.group(1)}{number:0{len(match.group(2))}d}"
        if new in out:
            raise PoseFileError(f"shifting frame numbers by {offset} makes two images {new!r}")
        out[new] = pose
    return out


def _keyed(entries: Iterable[tuple[str, np.ndarray]], path: Path) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    names: dict[str, str] = {}
    for name, c2w in entries:
        key = image_key(name)
        if key in out:
            raise PoseFileError(f"{path}: images {names[key]!r} and {name!r} share the matching key {key!r} "
                                "(base name without extension): rename one of them")
        out[key], names[key] = c2w, name
    if not out:
        raise PoseFileError(f"{path}: no camera poses in the file")
    return out


def _rigid(c2w: np.ndarray, what: str) -> np.ndarray:
    """Check a 4×4 camera→world: finite, proper orthonormal rotation (within :data:`ROTATION_TOL`)."""
    if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
        raise PoseFileError(f"{what}: the pose must be a finite 4×4 (or 3×4) matrix")
    rot = c2w[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=ROTATION_TOL) or np.linalg.det(rot) <= 0.0:
        raise PoseFileError(f"{what}: the pose's rotation is not orthonormal with determinant +1")
    return c2w


def _homogeneous(matrix, what: str) -> np.ndarray:
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PoseFileError(f"{what}: not a numeric matrix ({exc})") from exc
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise PoseFileError(f"{what}: expected a 4×4 or 3×4 matrix, got shape {m.shape}")
    return m


def _opengl_c2w_to_opencv_c2w(transform_matrix: np.ndarray) -> np.ndarray:
    """nerfstudio / Blender camera→world (x right, y up, z back) → OpenCV camera→world."""
    w2c = opengl_c2w_to_opencv_w2c(transform_matrix)
    c2w = np.eye(4)
    c2w[:3, :3] = w2c[:3, :3].T
    c2w[:3, 3] = -w2c[:3, :3].T @ w2c[:3, 3]
    return c2w


def _load_json(path: Path):
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise PoseFileError(f"{path}: not valid JSON ({exc})") from exc


def read_dataparser_transform(path: str | Path) -> tuple[np.ndarray, float]:
    """nerfstudio ``dataparser_transforms.json`` → (4×4 ``transform``, ``scale``): a point x of the data's
    original frame sits at ``scale·(transform·x)`` in the trained model's frame."""
    path = Path(path)
    meta = _load_json(path)
    if not isinstance(meta, dict) or "transform" not in meta or "scale" not in meta:
        raise PoseFileError(f"{path}: a dataparser_transforms.json holds 'transform' (3×4) and 'scale'")
    transform = _homogeneous(meta["transform"], f"{path}: transform")
    scale = meta["scale"]
    if not isinstance(scale, int | float) or not math.isfinite(scale) or scale <= 0:
        raise PoseFileError(f"{path}: 'scale' must be a finite number > 0, got {scale!r}")
    if not np.all(np.isfinite(transform)):
        raise PoseFileError(f"{path}: 'transform' holds NaN/inf")
    return transform, float(scale)


def _saved_to_model_frame(meta: dict, transforms_path: Path, dataparser_path: Path) -> tuple[np.ndarray, float]:
    """(T, s) with x_model = s·(T·x) for x in transforms.json's frame.

    nerfstudio's dataparser orients and centres the poses of transforms.json (``transform_matrix`` T_o,
    rigid) and scales them (s_o): the cameras it trains with are s_o·(T_o·pose). What it saves as
    ``dataparser_transforms.json`` is T_o·A (A = transforms.json's ``applied_transform``, which ns-process-data
    writes: COLMAP's frame → the saved one) and s_o·``applied_scale``; so T_o = T_saved·A⁻¹, s_o = s_saved /
    applied_scale. Without the key, nerfstudio takes its legacy COLMAP value when ``colmap/sparse/0`` sits
    beside transforms.json, and A = I otherwise.
    """
    transform, scale = read_dataparser_transform(dataparser_path)
    applied = meta.get("applied_transform")
    if applied is None and (transforms_path.parent / "colmap" / "sparse" / "0").is_dir():
        applied = NERFSTUDIO_LEGACY_APPLIED_TRANSFORM
    if applied is not None:
        a = _homogeneous(applied, f"{transforms_path}: applied_transform")
        if not np.all(np.isfinite(a)) or abs(np.linalg.det(a[:3, :3])) < 1e-12:
            raise PoseFileError(f"{transforms_path}: applied_transform is not an invertible finite transform")
        transform = transform @ np.linalg.inv(a)
    applied_scale = meta.get("applied_scale", 1.0)
    if not isinstance(applied_scale, int | float) or not math.isfinite(applied_scale) or applied_scale <= 0:
        raise PoseFileError(f"{transforms_path}: applied_scale must be a finite number > 0")
    rot = transform[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=ROTATION_TOL) or np.linalg.det(rot) <= 0.0:
        raise PoseFileError(f"{dataparser_path}: the dataparser transform (with {transforms_path.name}'s "
                            "applied_transform undone) is not a rotation and translation; is it the "
                            "dataparser_transforms.json of the run trained on this transforms.json?")
    return transform, scale / float(applied_scale)


def read_nerfstudio_transforms(path: str | Path, dataparser_transforms: str | Path | None = None
                               ) -> dict[str, np.ndarray]:
    """nerfstudio ``transforms.json`` (file or its folder) → ``{image_key(file_path): camera→world}``.

    Without ``dataparser_transforms`` the poses are in the file's own frame. With a splatfacto run's
    ``dataparser_transforms.json`` they are carried into the frame its Gaussians live in (and
    ``ns-export gaussian-splat`` writes them in): rotation T·R, centre s·(T·c) (see
    :func:`_saved_to_model_frame` for T and s). The file's ``applied_transform`` and ``applied_scale`` keys
    are honoured as nerfstudio's dataparser does.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    meta = _load_json(path)
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise PoseFileError(f"{path}: a nerfstudio transforms.json is an object with a 'frames' list")
    transform, scale = np.eye(4), 1.0
    if dataparser_transforms is not None:
        transform, scale = _saved_to_model_frame(meta, path, Path(dataparser_transforms))
    entries = []
    for i, frame in enumerate(meta["frames"]):
        what = f"{path}: frame {i}"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise PoseFileError(f"{what}: needs 'file_path' and 'transform_matrix'")
        c2w = _opengl_c2w_to_opencv_c2w(_rigid(_homogeneous(frame["transform_matrix"], what), what))
        c2w = transform @ c2w
        c2w[:3, 3] *= scale
        entries.append((str(frame["file_path"]), c2w))
    return _keyed(entries, path)


def read_nerfstudio_exported_cameras(path: str | Path) -> dict[str, np.ndarray]:
    """``ns-export cameras`` output (``transforms_train.json`` / ``transforms_eval.json``: a list of
    ``{"file_path", "transform"}``, camera→world 3×4 in OpenGL axes, in the model's dataparser frame and
    with nerfstudio's camera optimisation applied) → ``{image_key(file_path): camera→world}``."""
    path = Path(path)
    data = _load_json(path)
    if not isinstance(data, list):
        raise PoseFileError(f"{path}: ns-export cameras writes a JSON list of {{'file_path', 'transform'}}")
    entries = []
    for i, frame in enumerate(data):
        what = f"{path}: camera {i}"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform" not in frame:
            raise PoseFileError(f"{what}: needs 'file_path' and 'transform'")
        c2w = _opengl_c2w_to_opencv_c2w(_rigid(_homogeneous(frame["transform"], what), what))
        entries.append((str(frame["file_path"]), c2w))
    return _keyed(entries, path)


def read_colmap_images_txt(path: str | Path) -> dict[str, np.ndarray]:
    """COLMAP text model ``images.txt`` → ``{image_key(NAME): camera→world}``.

    Each image takes two lines: ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` — the world→camera rotation
    as a unit quaternion (Hamilton, w first) and translation, x_cam = R·x_world + t, OpenCV axes — then its
    2-D points (possibly an empty line). Lines starting with ``#`` are comments. The camera→world pose is
    [Rᵀ | −Rᵀ·t].
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    lines = path.read_text().splitlines()
    entries = []
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        if not line or line.startswith("#"):
            i += 1
            continue
        fields = line.split()
        what = f"{path}: line {i + 1}"
        if len(fields) < 10:
            raise PoseFileError(f"{what}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got {line!r}")
        try:
            q_wxyz = np.array([float(v) for v in fields[1:5]])
            t = np.array([float(v) for v in fields[5:8]])
        except ValueError as exc:
            raise PoseFileError(f"{what}: {exc}") from exc
        norm = float(np.linalg.norm(q_wxyz))
        if not (np.all(np.isfinite(q_wxyz)) and np.all(np.isfinite(t)) and norm > 0.0):
            raise PoseFileError(f"{what}: the quaternion and translation must be finite, the quaternion non-zero")
        rot = Rotation.from_quat(q_wxyz[[1, 2, 3, 0]] / norm).as_matrix()  # scipy wants (x, y, z, w)
        c2w = np.eye(4)
        c2w[:3, :3] = rot.T
        c2w[:3, 3] = -rot.T @ t
        entries.append((" ".join(fields[9:]), c2w))
        i += 2  # the next line holds the image's 2-D points
    return _keyed(entries, path)


def read_3dgs_cameras_json(path: str | Path) -> dict[str, np.ndarray]:
    """graphdeco-inria 3DGS ``cameras.json`` → ``{image_key(img_name): camera→world}``.

    ``camera_to_JSON`` builds Rt = [Rᵀ | T] — 3DGS keeps R = (COLMAP world→camera rotation)ᵀ and T = COLMAP's
    translation, so Rt is world→camera — and writes its inverse: ``position`` = the camera centre in the world
    and ``rotation`` = the camera→world rotation (rows of the 3×3 as stored; columns = the camera's x, y, z
    axes in the world, OpenCV axes). So camera→world = [rotation | position], in the COLMAP (or Blender,
    axes flipped to OpenCV on load) frame the model was trained in.
    """
    path = Path(path)
    data = _load_json(path)
    if not isinstance(data, list):
        raise PoseFileError(f"{path}: a 3DGS cameras.json is a JSON list of cameras")
    entries = []
    for i, cam in enumerate(data):
        what = f"{path}: camera {i}"
        if not isinstance(cam, dict) or not {"img_name", "position", "rotation"} <= set(cam):
            raise PoseFileError(f"{what}: needs 'img_name', 'position' and 'rotation'")
        try:
            rot = np.asarray(cam["rotation"], dtype=np.float64)
            pos = np.asarray(cam["position"], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise PoseFileError(f"{what}: {exc}") from exc
        if rot.shape != (3, 3) or pos.shape != (3,):
            raise PoseFileError(f"{what}: 'rotation' must be 3×3 and 'position' 3 numbers")
        c2w = np.eye(4)
        c2w[:3, :3] = rot
        c2w[:3, 3] = pos
        entries.append((str(cam["img_name"]), _rigid(c2w, what)))
    return _keyed(entries, path)


def read_map_dataset(root: str | Path) -> dict[str, np.ndarray]:
    """A gsrmr nerfstudio dataset (folder or transforms.json, :func:`gsrmr_common.nerfstudio.read_dataset`,
    images not loaded) → ``{image_key(file_path): camera→world}`` in ``map`` (metres, REP-103)."""
    root = Path(root)
    frames = read_dataset(root, load_images=False)
    return _keyed(((f.file_path, f.camera.camera_to_world) for f in frames), root)


def detect_format(path: str | Path) -> str:
    """Which reader a model-side pose file needs: ``"colmap"`` (a ``.txt``), else by the JSON's content:
    ``"nerfstudio"`` (an object with ``frames``), ``"3dgs"`` (a list of objects with ``img_name``),
    ``"ns-export"`` (a list of objects with ``file_path`` and ``transform``). PoseFileError otherwise."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such file: {path}")
    if path.is_dir():
        path = path / "transforms.json"
    if path.suffix.lower() == ".bin":
        raise PoseFileError(f"{path}: a binary COLMAP model; convert it to text with `colmap model_converter "
                            "--input_path DIR --output_path DIR --output_type TXT` and pass images.txt")
    if path.suffix.lower() == ".txt":
        return "colmap"
    data = _load_json(path)
    if isinstance(data, dict) and "frames" in data:
        return "nerfstudio"
    if isinstance(data, list) and data and isinstance(data[0], dict):
        if "img_name" in data[0]:
            return "3dgs"
        if "file_path" in data[0] and "transform" in data[0]:
            return "ns-export"
    raise PoseFileError(f"{path}: not a pose file this tool reads (nerfstudio transforms.json, ns-export cameras "
                        "JSON, 3DGS cameras.json or COLMAP images.txt)")


def read_model_poses(path: str | Path, dataparser_transforms: str | Path | None = None) -> dict[str, np.ndarray]:
    """The model-side camera poses from any supported file (:func:`detect_format`); ``dataparser_transforms``
    only with a nerfstudio transforms.json (PoseFileError otherwise)."""
    fmt = detect_format(path)
    if dataparser_transforms is not None and fmt != "nerfstudio":
        raise PoseFileError(f"{path}: a dataparser_transforms.json applies to a nerfstudio transforms.json only "
                            f"(this file is {fmt}); drop --dataparser-transforms")
    path = Path(path)
    if fmt == "nerfstudio":
        return read_nerfstudio_transforms(path, dataparser_transforms)
    if fmt == "ns-export":
        return read_nerfstudio_exported_cameras(path)
    if fmt == "3dgs":
        return read_3dgs_cameras_json(path)
    return read_colmap_images_txt(path)
