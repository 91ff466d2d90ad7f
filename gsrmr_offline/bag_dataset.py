"""A robot's recorded round (a bag) → a nerfstudio dataset in the world frame: the pipeline of ``gsrmr-dataset``
(:func:`build_dataset`) — topics (:mod:`~gsrmr_offline.bag_topics`), camera poses (:mod:`~gsrmr_offline.bag_poses`),
the sync rule, keyframes (:mod:`~gsrmr_offline.keyframes`) and the output, by the rules of docs/dataset_tool.md.
Deterministic: the same bag and options give byte-identical files; bad input raises :class:`DatasetInputError`.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
import csv
from dataclasses import dataclass, field
import io
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from gsrmr_common.calibration import CalibrationError, CameraCalibration, Rectifier
from gsrmr_common.camera import Camera, Intrinsics
from gsrmr_common.config_files import resolve_config
from gsrmr_common.image_decode import (
    COMPRESSED_TYPE,
    ImageDecodeError,
    decode_colour,
    decode_depth_m,
    format_stamp,
    is_depth_message,
    stamp_ns,
)
from gsrmr_common.nerfstudio import DatasetFrame, DatasetWriter
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.tf_buffer import (
    NS_PER_S,
    OUT_OF_RANGE,
    TfBuffer,
    TfLookupError,
    invert,
    rotation_angle_rad,
    strip_frame,
)
from gsrmr_common.tf_tree import BASE_FRAME, MAP_FRAME, base_from_camera_optical_transform
from gsrmr_offline.bag_poses import (
    POSE_TYPES,
    TF_STATIC_TOPIC,
    TF_TOPIC,
    add_tf_message,
    pose_child_frame,
    pose_edge,
    read_camera_mount,
)
from gsrmr_offline.bag_reader import BagError, BagMessage, BagReader, BagTopic
from gsrmr_offline.bag_topics import (
    describe_topics,
    has_depth_name,
    has_infrared_name,
    image_topics,
    sibling_camera_info,
    strip_transport,
)
from gsrmr_offline.keyframes import blurred, laplacian_variance, spaced, thin_evenly

CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
KEPT = "kept"
DECODE_ERROR = "decode_error"
SIZE_MISMATCH = "size_mismatch"
BLUR = "blur"
KEYFRAME_SKIP = "keyframe_skip"
MAX_FRAMES = "max_frames"
#: Every status of a frame, in the order its rule applies (``kept`` last).
STATUSES = ("no_tf_path", OUT_OF_RANGE, "gap", DECODE_ERROR, SIZE_MISMATCH, BLUR, KEYFRAME_SKIP, MAX_FRAMES, KEPT)
#: Columns of ``frames.csv`` (docs/dataset_tool.md describes each).
CSV_COLUMNS = ("index", "stamp_s", "frame_id", "status", "file_path", "gap_s", "speed_mps", "angular_speed_radps",
               "motion_bound_m", "motion_bound_rad", "sharpness", "depth_offset_s")
VELOCITY_HALF_WINDOW_NS = 5_000_000  # camera speed: chain poses ±5 ms around the stamp


class DatasetInputError(ValueError):
    """Input the tool cannot turn into a dataset: one line, what is wrong and the fix."""


@dataclass(frozen=True)
class BagDatasetOptions:
    """What ``gsrmr-dataset`` is asked to do (the CLI's options; units in the names)."""

    bag: Path
    out: Path
    image_topic: str | None = None
    camera_info_topic: str | None = None
    camera_info_file: Path | None = None
    depth_topic: str | None = None
    use_depth: bool = True
    world_frame: str = MAP_FRAME
    base_frame: str = BASE_FRAME
    camera_frame: str | None = None
    pose_topic: str | None = None
    camera_mount_file: Path | None = None
    max_gap_s: float = 0.1
    blur_ratio: float = 0.5
    blur_window: int = 5
    min_translation_m: float = 0.05
    min_rotation_deg: float = 5.0
    max_frames: int | None = None
    depth_max_offset_s: float = 0.02


@dataclass
class FrameRecord:
    """One image read from the bag and what became of it (a row of ``frames.csv``)."""

    index: int  # position in the image topic, in read order
    stamp_ns: int  # header.stamp
    frame_id: str
    status: str = ""
    gap_s: float | None = None  # widest bracket on the chain's moving edges
    speed_mps: float | None = None
    angular_speed_radps: float | None = None
    sharpness: float | None = None
    camera_to_world: np.ndarray | None = field(default=None, repr=False)
    robot_pose: Pose2D | None = None  # base frame (a_m, b_m, theta_rad) in the world frame
    depth_index: int | None = None
    depth_offset_s: float | None = None
    file_path: str = ""

    def csv_row(self) -> list[str]:
        """The row of ``frames.csv`` (fixed formats; empty where unknown)."""
        def num(value: float | None, digits: int) -> str:
            return "" if value is None else f"{value:.{digits}f}"
        bound_m = None if self.speed_mps is None or self.gap_s is None else self.speed_mps * self.gap_s
        bound_rad = None if self.angular_speed_radps is None or self.gap_s is None else \
            self.angular_speed_radps * self.gap_s
        return [str(self.index), format_stamp(self.stamp_ns), self.frame_id, self.status, self.file_path,
                num(self.gap_s, 6), num(self.speed_mps, 6), num(self.angular_speed_radps, 6), num(bound_m, 6),
                num(bound_rad, 6), num(self.sharpness, 3), num(self.depth_offset_s, 6)]


@dataclass
class DatasetReport:
    """What a run did: every frame, the choices made and the warnings (:attr:`notes`)."""

    frames: list[FrameRecord]
    image_topic: str
    depth_topic: str | None
    calibration_source: str
    pose_source: str
    intrinsics: Intrinsics
    out: Path
    notes: list[str] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        """Frames per status, in the order of :data:`STATUSES` (only those that occur)."""
        found = Counter(f.status for f in self.frames)
        return {s: found[s] for s in STATUSES if found[s]}

    def summary_line(self) -> str:
        """``N frames read from T, K kept, D dropped (reason n, …); wrote OUT/transforms.json (…)``."""
        counts = self.counts()
        kept = counts.get(KEPT, 0)
        dropped = {s: n for s, n in counts.items() if s != KEPT}
        reasons = ", ".join(f"{s} {n}" for s, n in dropped.items())
        with_depth = sum(1 for f in self.frames if f.status == KEPT and f.depth_index is not None)
        k = self.intrinsics
        return (f"{len(self.frames)} frames read from {self.image_topic}, {kept} kept, {sum(dropped.values())} "
                f"dropped{f' ({reasons})' if reasons else ''}; poses from {self.pose_source}; wrote "
                f"{self.out / 'transforms.json'} ({k.width}×{k.height} rectified, {with_depth} with depth)")


# -------------------------------------------------------------------------------------------------- topics

def _topic_error(bag: BagReader, what: str) -> DatasetInputError:
    return DatasetInputError(f"{what}; the bag's image topics: {describe_topics(image_topics(bag.topics))} — "
                             "pass --image-topic TOPIC")


def _is_colour_topic(bag: BagReader, topic: BagTopic) -> bool:
    if has_depth_name(topic.name) or has_infrared_name(topic.name):
        return False
    first = bag.first(topic.name)
    return first is not None and not is_depth_message(first.msg, first.msgtype)


def select_colour_topic(bag: BagReader, wanted: str | None) -> str:
    """The colour image topic: ``wanted`` (checked), else the bag's only colour topic (:mod:`bag_topics`)."""
    topics = bag.topics
    if wanted is not None:
        if wanted not in topics:
            raise _topic_error(bag, f"no topic {wanted} in {bag.path}")
        if topics[wanted].msgtype not in ("sensor_msgs/msg/Image", COMPRESSED_TYPE):
            raise _topic_error(bag, f"{wanted} carries {topics[wanted].msgtype}, not images")
        return wanted
    candidates = [t for t in image_topics(topics) if _is_colour_topic(bag, t)]
    if not candidates:
        raise _topic_error(bag, f"{bag.path} has no colour image topic (depth and infrared topics are not colour)")
    if len({strip_transport(t.name) for t in candidates}) == 1:  # one camera, raw and republished: the raw one
        candidates.sort(key=lambda t: (t.msgtype == COMPRESSED_TYPE, t.name))
        return candidates[0].name
    if len(candidates) > 1:
        raise DatasetInputError(f"{bag.path} has {len(candidates)} colour image topics: "
                                f"{describe_topics(candidates)} — pass --image-topic TOPIC")
    return candidates[0].name


def _camera_info_fields(msg: Any) -> Any:
    """A CameraInfo as :meth:`CameraCalibration.from_camera_info` reads it (ROS 1 names ``K D R P`` → lower)."""
    if hasattr(msg, "k"):
        return msg
    return SimpleNamespace(header=msg.header, width=msg.width, height=msg.height, k=msg.K, d=msg.D, r=msg.R,
                           p=msg.P, distortion_model=msg.distortion_model)


def load_calibration(bag: BagReader, options: BagDatasetOptions, colour_topic: str) -> tuple[CameraCalibration, str]:
    """The camera's calibration and where it came from (a file, or the first CameraInfo of the topic)."""
    if options.camera_info_file is not None:
        try:
            return CameraCalibration.from_yaml(options.camera_info_file), str(options.camera_info_file)
        except CalibrationError as err:
            raise DatasetInputError(f"--camera-info: {err}") from None
    topic = options.camera_info_topic or sibling_camera_info(colour_topic)
    infos = [t for t in bag.topics.values() if t.msgtype == CAMERA_INFO_TYPE]
    first = bag.first(topic) if topic in bag.topics else None
    if first is None:
        which = "given by --camera-info-topic" if options.camera_info_topic else f"the sibling of {colour_topic}"
        raise DatasetInputError(f"no CameraInfo on {topic} ({which}) and no --camera-info FILE; the bag's CameraInfo "
                                f"topics: {describe_topics(infos)} — pass --camera-info-topic TOPIC, or --camera-info "
                                "FILE (a camera_calibration YAML)")
    if first.msgtype != CAMERA_INFO_TYPE:
        raise DatasetInputError(f"{topic} carries {first.msgtype}, not sensor_msgs/CameraInfo — pass "
                                "--camera-info-topic TOPIC or --camera-info FILE")
    try:
        return CameraCalibration.from_camera_info(_camera_info_fields(first.msg)), topic
    except CalibrationError as err:
        raise DatasetInputError(f"the CameraInfo on {topic}: {err}") from None


def _decoded_size(message: BagMessage, depth: bool) -> tuple[int, int]:
    img = decode_depth_m(message.msg, message.msgtype) if depth else decode_colour(message.msg, message.msgtype)
    return int(img.shape[1]), int(img.shape[0])


def select_depth_topic(bag: BagReader, options: BagDatasetOptions, colour_topic: str, colour_frames: set[str],
                       calib: CameraCalibration) -> tuple[str | None, list[str]]:
    """The aligned depth topic (``--depth-topic`` checked, else auto-detected by the rule of :mod:`bag_topics`)
    and notes on the depth topics passed over."""
    if not options.use_depth:
        return None, []
    notes: list[str] = []
    size = (calib.width, calib.height)

    def check(topic: BagTopic) -> str | None:
        """Why ``topic`` cannot be the aligned depth (``None`` if it can)."""
        first = bag.first(topic.name)
        if first is None:
            return "it has no message"
        if not is_depth_message(first.msg, first.msgtype):
            return "its first message is not depth (16UC1, mono16, 32FC1, compressedDepth)"
        frame = strip_frame(first.msg.header.frame_id)
        if frame not in colour_frames:
            return (f"it is in frame {frame or '(empty)'}, the colour images in {' / '.join(sorted(colour_frames))}: "
                    "only depth registered to the colour camera (aligned_depth_to_color, depth_registered) applies")
        try:
            got = _decoded_size(first, depth=True)
        except ImageDecodeError as err:
            return f"its first message cannot be decoded ({err})"
        if got != size:
            return f"it is {got[0]}×{got[1]}, the colour camera {size[0]}×{size[1]}"
        return None

    if options.depth_topic is not None:
        if options.depth_topic not in bag.topics:
            raise _topic_error(bag, f"no depth topic {options.depth_topic} in {bag.path}")
        if options.depth_topic == colour_topic:
            raise DatasetInputError(f"--depth-topic {colour_topic} is the colour topic — pass the depth topic")
        why = check(bag.topics[options.depth_topic])
        if why is not None:
            raise DatasetInputError(f"--depth-topic {options.depth_topic}: {why} — pass another depth topic or "
                                    "--no-depth")
        return options.depth_topic, notes
    usable = []
    for topic in image_topics(bag.topics):
        if topic.name == colour_topic:
            continue
        first = bag.first(topic.name)
        if not has_depth_name(topic.name) and (first is None or not is_depth_message(first.msg, first.msgtype)):
            continue
        why = check(topic)
        if why is None:
            usable.append(topic)
        else:
            notes.append(f"depth topic {topic.name} not used: {why}")
    if not usable:
        return None, notes
    usable.sort(key=lambda t: (t.msgtype == COMPRESSED_TYPE, t.name))
    return usable[0].name, notes


# --------------------------------------------------------------------------------------------------- poses

def _default_mount_file() -> Path:
    try:
        return resolve_config("camera_mount", "", "camera mount")
    except FileNotFoundError as err:
        raise DatasetInputError(f"{err} — pass --camera-mount FILE") from None


def _connected(buffer: TfBuffer, a: str, b: str) -> bool:
    try:
        buffer.chain(a, b)
    except TfLookupError:
        return False
    return True


def build_pose_tree(bag: BagReader, options: BagDatasetOptions, camera_frame: str) -> tuple[TfBuffer, str, list[str]]:
    """The TF tree the cameras are looked up in, a description of the pose source, and notes."""
    buffer = TfBuffer()
    notes: list[str] = []
    topics = bag.topics
    wanted = [t for t in (TF_TOPIC, TF_STATIC_TOPIC) if t in topics]
    skip: frozenset[str] = frozenset()
    pose_child = None
    if options.pose_topic is not None:
        poses = [t for t in topics.values() if t.msgtype in POSE_TYPES]
        if options.pose_topic not in topics or topics[options.pose_topic].msgtype not in POSE_TYPES:
            what = "no topic" if options.pose_topic not in topics else \
                f"{topics[options.pose_topic].msgtype} is not a pose type on"
            raise DatasetInputError(f"{what} {options.pose_topic} in {bag.path}; its pose topics (Odometry, "
                                    f"PoseStamped, PoseWithCovarianceStamped): {describe_topics(poses)} — pass "
                                    "--pose-topic with one of them")
        first = bag.first(options.pose_topic)
        if first is None:
            raise DatasetInputError(f"{options.pose_topic} has no message — pass another --pose-topic")
        pose_child = pose_child_frame(first.msg, first.msgtype, options.base_frame)
        skip = frozenset({pose_child})
        wanted.append(options.pose_topic)
    bad = 0
    for message in bag.messages(wanted):
        if message.topic == options.pose_topic:
            try:
                parent, child, stamp, transform = pose_edge(message.msg, message.msgtype, options.base_frame)
                buffer.add_sample(parent, child, stamp, transform)
            except ValueError:
                bad += 1
        elif hasattr(message.msg, "transforms"):
            bad += add_tf_message(buffer, message.msg, message.topic == TF_STATIC_TOPIC, skip)
    if bad:
        notes.append(f"{bad} transforms or poses with bad numbers or frame names were ignored")
    if buffer.parent_conflicts:
        notes.append("frames published under two parents (the first parent kept): " + ", ".join(
            f"{child} ({', '.join(sorted(p))})" for child, p in sorted(buffer.parent_conflicts.items())))
    world = strip_frame(options.world_frame)
    anchor = pose_child if pose_child is not None else strip_frame(options.base_frame)
    source = f"TF {world} → {camera_frame}" if pose_child is None else \
        f"{options.pose_topic} ({pose_child} in its frame) ∘ camera mount"
    mount_file = options.camera_mount_file
    if pose_child is not None and mount_file is None:
        mount_file = _default_mount_file()
    need_mount = not _connected(buffer, anchor if pose_child is not None else world, camera_frame)
    if need_mount and mount_file is not None:
        try:
            mount = read_camera_mount(mount_file)
        except ValueError as err:
            raise DatasetInputError(f"--camera-mount: {err}") from None
        if buffer.remove_edge_into(camera_frame):
            notes.append(f"{camera_frame} was not connected to {anchor}: its TF parent is replaced by the mount")
        buffer.set_static(anchor, camera_frame, base_from_camera_optical_transform(mount))
        source += f" (mount {anchor} → {camera_frame} from {Path(mount_file).name})"
    elif pose_child is not None:
        source += f" (mount {anchor} → {camera_frame} from the bag's TF)"
    if not need_mount and options.camera_mount_file is not None:
        notes.append(f"--camera-mount not used: the bag's TF already places {camera_frame}")
    try:
        buffer.chain(world, camera_frame)
    except TfLookupError:
        missing_static = "" if TF_STATIC_TOPIC in topics else " (the bag has no /tf_static)"
        raise DatasetInputError(
            f"no TF path from {world} to {camera_frame}: the tree has {buffer.describe_tree()}{missing_static} — "
            "record /tf and /tf_static (with the transient_local QoS override: docs/dataset_tool.md), or pass "
            "--world-frame/--camera-frame, or --camera-mount FILE for the base → camera mount") from None
    return buffer, source, notes


def _camera_velocity(buffer: TfBuffer, world: str, frame: str, stamp: int) -> tuple[float | None, float | None]:
    """Linear [m/s] and angular [rad/s] speed of ``frame`` in ``world`` around ``stamp`` (central difference over
    ±5 ms, one-sided at the ends of the pose range)."""
    for t0, t1 in ((stamp - VELOCITY_HALF_WINDOW_NS, stamp + VELOCITY_HALF_WINDOW_NS),
                   (stamp, stamp + VELOCITY_HALF_WINDOW_NS), (stamp - VELOCITY_HALF_WINDOW_NS, stamp)):
        try:
            a = buffer.lookup(world, frame, t0).target_from_source
            b = buffer.lookup(world, frame, t1).target_from_source
        except TfLookupError:
            continue
        dt = (t1 - t0) / NS_PER_S
        return (float(np.linalg.norm(b[:3, 3] - a[:3, 3])) / dt,
                rotation_angle_rad(a[:3, :3].T @ b[:3, :3]) / dt)
    return None, None


def _planar_pose(matrix: np.ndarray) -> Pose2D:
    return float(matrix[0, 3]), float(matrix[1, 3]), math.atan2(float(matrix[1, 0]), float(matrix[0, 0]))


# -------------------------------------------------------------------------------------------------- frames

@dataclass(frozen=True)
class _Scan:
    frames: list[FrameRecord]
    depth_stamps: list[tuple[int, int]]  # (stamp_ns, depth index)


def scan_frames(bag: BagReader, options: BagDatasetOptions, colour_topic: str, depth_topic: str | None,
                buffer: TfBuffer, calib: CameraCalibration, default_frame: str) -> _Scan:
    """Every image of the colour topic: its camera pose (sync rule), speed, sharpness, robot pose; and the depth
    topic's stamps."""
    world, base = strip_frame(options.world_frame), strip_frame(options.base_frame)
    base_known = buffer.has_frame(base) and _connected(buffer, world, base)
    frames: list[FrameRecord] = []
    depth_stamps: list[tuple[int, int]] = []
    for message in bag.messages([colour_topic] + ([depth_topic] if depth_topic else [])):
        if message.topic == depth_topic:
            depth_stamps.append((stamp_ns(message.msg.header.stamp), len(depth_stamps)))
            continue
        frame_id = strip_frame(options.camera_frame or message.msg.header.frame_id) or default_frame
        record = FrameRecord(len(frames), stamp_ns(message.msg.header.stamp), frame_id)
        frames.append(record)
        try:
            look = buffer.lookup(world, frame_id, record.stamp_ns, options.max_gap_s)
            record.camera_to_world, record.gap_s = look.target_from_source, look.widest_gap_s
        except TfLookupError as err:
            record.status, record.gap_s = err.reason, err.widest_gap_s
        if record.status in ("", "gap"):
            record.speed_mps, record.angular_speed_radps = _camera_velocity(buffer, world, frame_id, record.stamp_ns)
        if record.status:
            continue
        try:
            rgb = decode_colour(message.msg, message.msgtype)
        except ImageDecodeError:
            record.status = DECODE_ERROR
            continue
        if (rgb.shape[1], rgb.shape[0]) != (calib.width, calib.height):
            record.status = SIZE_MISMATCH
            continue
        record.sharpness = laplacian_variance(rgb)
        if base_known:
            try:
                record.robot_pose = _planar_pose(buffer.lookup(world, base, record.stamp_ns).target_from_source)
            except TfLookupError:
                record.robot_pose = None
    return _Scan(frames, depth_stamps)


def select_keyframes(frames: list[FrameRecord], options: BagDatasetOptions) -> None:
    """Blur, spacing and thinning over the synced frames in time order; sets each one's status."""
    synced = sorted((f for f in frames if not f.status), key=lambda f: (f.stamp_ns, f.index))
    for frame, is_blurred in zip(synced, blurred([f.sharpness or 0.0 for f in synced], options.blur_window,
                                                 options.blur_ratio), strict=True):
        if is_blurred:
            frame.status = BLUR
    sharp = [f for f in synced if not f.status]
    for frame, keep in zip(sharp, spaced([f.camera_to_world for f in sharp], options.min_translation_m,
                                         options.min_rotation_deg), strict=True):
        if not keep:
            frame.status = KEYFRAME_SKIP
    spread = [f for f in sharp if not f.status]
    chosen = set(thin_evenly(len(spread), options.max_frames))
    for i, frame in enumerate(spread):
        frame.status = KEPT if i in chosen else MAX_FRAMES


def pair_depth(frames: Iterable[FrameRecord], depth_stamps: list[tuple[int, int]], max_offset_s: float) -> None:
    """Give each kept frame the depth image nearest its stamp, if within ``max_offset_s`` (ties: the earlier)."""
    if not depth_stamps:
        return
    stamps = np.array([s for s, _i in depth_stamps], dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    for frame in frames:
        if frame.status != KEPT:
            continue
        j = int(np.searchsorted(stamps, frame.stamp_ns))
        best = min((k for k in (j - 1, j) if 0 <= k < len(stamps)),
                   key=lambda k: (abs(int(stamps[k]) - frame.stamp_ns), k))
        offset_s = (int(stamps[best]) - frame.stamp_ns) / NS_PER_S
        if abs(offset_s) <= max_offset_s:
            frame.depth_index, frame.depth_offset_s = depth_stamps[int(order[best])][1], offset_s


def _no_frame_error(frames: list[FrameRecord], colour_topic: str, buffer: TfBuffer, world: str, camera_frame: str,
                    pose_source: str, max_gap_s: float) -> DatasetInputError:
    counts = Counter(f.status for f in frames)
    if not frames:
        return DatasetInputError(f"{colour_topic} has no readable message — check the topic and the bag")
    stamps = [f.stamp_ns for f in frames]
    image_range = f"{format_stamp(min(stamps))[:-6]}–{format_stamp(max(stamps))[:-6]} s"
    if counts[OUT_OF_RANGE] == len(frames):
        span = buffer.time_range_ns(world, camera_frame)
        pose_range = "none" if span is None else f"{format_stamp(span[0])[:-6]}–{format_stamp(span[1])[:-6]} s"
        edges = ", ".join(f"{p} → {c}" for p, c in buffer.moving_edges(world, camera_frame))
        return DatasetInputError(
            f"all {len(frames)} frames of {colour_topic} are outside the pose range: image stamps {image_range}, "
            f"{pose_source} {pose_range} (moving edges {edges}) — images and poses must be stamped on one clock "
            "(use_sim_time on one side only?) and overlap in time")
    if counts["gap"] and not any(f.status in ("", KEPT) for f in frames):
        widest = max((f.gap_s or 0.0) for f in frames if f.status == "gap")
        return DatasetInputError(
            f"no frame of {colour_topic} has poses within --max-gap-s {max_gap_s:g} s around it (gaps up to "
            f"{widest:.3f} s; image stamps {image_range}) — record /tf at a higher rate or raise --max-gap-s")
    reasons = ", ".join(f"{s} {counts[s]}" for s in STATUSES if counts[s])
    return DatasetInputError(f"no frame of {colour_topic} kept ({reasons}) — see the sync and keyframe options "
                             "(--max-gap-s, --blur-ratio, --camera-frame)")


# -------------------------------------------------------------------------------------------------- output

OUTPUT_FILES = ("transforms.json", "frames.csv")
OUTPUT_GLOBS = ("images/frame_*.png", "depths/frame_*.png")


def clear_output(out: Path) -> None:
    """Remove what an earlier run of the tool wrote in ``out`` (its own file names only)."""
    for name in OUTPUT_FILES:
        (out / name).unlink(missing_ok=True)
    for pattern in OUTPUT_GLOBS:
        for path in out.glob(pattern):
            path.unlink()


def write_frames_csv(path: Path, frames: list[FrameRecord]) -> None:
    """``frames.csv``: one row per image read (time order), :data:`CSV_COLUMNS`."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for frame in sorted(frames, key=lambda f: (f.stamp_ns, f.index)):
        writer.writerow(frame.csv_row())
    path.write_text(buf.getvalue())


def write_frames(bag: BagReader, frames: list[FrameRecord], colour_topic: str, depth_topic: str | None,
                 rectifier: Rectifier, out: Path) -> list[str]:
    """Read the kept frames (and their depth) again, rectify and write them; returns notes."""
    kept = sorted((f for f in frames if f.status == KEPT), key=lambda f: (f.stamp_ns, f.index))
    number = {f.index: k for k, f in enumerate(kept)}
    by_index = {f.index: f for f in kept}
    wanted_depth: dict[int, list[FrameRecord]] = {}
    for frame in kept:
        if frame.depth_index is not None:
            wanted_depth.setdefault(frame.depth_index, []).append(frame)
    writer = DatasetWriter(out)
    intrinsics = rectifier.intrinsics
    colour: dict[int, np.ndarray] = {}  # frame index → rectified RGB waiting for its depth
    depth: dict[int, np.ndarray | None] = {}  # depth index → rectified metres (None: undecodable)
    notes: list[str] = []

    def emit(frame: FrameRecord, rgb: np.ndarray, depth_m: np.ndarray | None) -> None:
        camera = Camera(intrinsics, invert(frame.camera_to_world))
        frame.file_path = writer.add(DatasetFrame(camera, rgb, depth_m, frame.robot_pose), number[frame.index])
        if depth_m is None:
            frame.depth_index = frame.depth_offset_s = None

    i_colour = i_depth = 0
    for message in bag.messages([colour_topic] + ([depth_topic] if depth_topic else [])):
        if message.topic == depth_topic:
            j, i_depth = i_depth, i_depth + 1
            if j not in wanted_depth:
                continue
            try:
                depth_m = rectifier.rectify_depth(decode_depth_m(message.msg, message.msgtype))
            except (ImageDecodeError, CalibrationError) as err:
                notes.append(f"depth message {j} of {depth_topic} cannot be decoded ({err}): frames without depth")
                depth_m = None
            depth[j] = depth_m
            for frame in wanted_depth[j]:
                if frame.index in colour:
                    emit(frame, colour.pop(frame.index), depth_m)
            continue
        i, i_colour = i_colour, i_colour + 1
        frame = by_index.get(i)
        if frame is None:
            continue
        rgb = rectifier(decode_colour(message.msg, message.msgtype))
        if frame.depth_index is None:
            emit(frame, rgb, None)
        elif frame.depth_index in depth:
            emit(frame, rgb, depth[frame.depth_index])
        else:
            colour[i] = rgb
    for i, rgb in sorted(colour.items()):
        emit(by_index[i], rgb, None)
        notes.append(f"frame {i}: its depth message was not found on the second read: written without depth")
    if len(number) != sum(1 for f in kept if f.file_path):
        missing = [f.index for f in kept if not f.file_path]
        raise DatasetInputError(f"frames {missing[:5]} of {colour_topic} could not be read a second time — the bag "
                                "changed while it was read?")
    writer.finish()
    return notes


# ---------------------------------------------------------------------------------------------- the pipeline

def build_dataset(options: BagDatasetOptions) -> DatasetReport:
    """Turn ``options.bag`` into a nerfstudio dataset in ``options.out`` (docs/dataset_tool.md). Raises
    :class:`DatasetInputError` (one line) on bad input."""
    try:
        bag = BagReader(options.bag)
    except BagError as err:
        raise DatasetInputError(str(err)) from None
    with bag:
        colour_topic = select_colour_topic(bag, options.image_topic)
        first = bag.first(colour_topic)
        if first is None:
            raise DatasetInputError(f"{colour_topic} has no readable message — pass another --image-topic")
        calib, calib_source = load_calibration(bag, options, colour_topic)
        header_frame = strip_frame(first.msg.header.frame_id)
        camera_frame = strip_frame(options.camera_frame or header_frame or calib.frame_id)
        if not camera_frame:
            raise DatasetInputError(f"the images on {colour_topic} have no header.frame_id and the calibration names "
                                    "no frame — pass --camera-frame FRAME (the camera's optical frame)")
        try:
            size = _decoded_size(first, depth=False)
        except ImageDecodeError as err:
            raise DatasetInputError(f"the first image of {colour_topic} cannot be decoded: {err}") from None
        if size != (calib.width, calib.height):
            raise DatasetInputError(f"the images on {colour_topic} are {size[0]}×{size[1]} but the calibration "
                                    f"({calib_source}) is for {calib.width}×{calib.height} — pass the calibration of "
                                    "this resolution with --camera-info FILE")
        colour_frames = {f for f in (header_frame, camera_frame) if f}
        depth_topic, depth_notes = select_depth_topic(bag, options, colour_topic, colour_frames, calib)
        buffer, pose_source, pose_notes = build_pose_tree(bag, options, camera_frame)
        scan = scan_frames(bag, options, colour_topic, depth_topic, buffer, calib, camera_frame)
        select_keyframes(scan.frames, options)
        if not any(f.status == KEPT for f in scan.frames):
            raise _no_frame_error(scan.frames, colour_topic, buffer, strip_frame(options.world_frame), camera_frame,
                                  pose_source, options.max_gap_s)
        pair_depth(scan.frames, scan.depth_stamps, options.depth_max_offset_s)
        rectifier = Rectifier(calib)
        options.out.mkdir(parents=True, exist_ok=True)
        clear_output(options.out)
        write_notes = write_frames(bag, scan.frames, colour_topic, depth_topic, rectifier, options.out)
        write_frames_csv(options.out / "frames.csv", scan.frames)
        notes = [*bag.notes, *depth_notes, *pose_notes, *write_notes]
        notes += [f"{n} messages of {t} could not be deserialised and were skipped" for t, n in
                  sorted(bag.skipped.items())]
        return DatasetReport(scan.frames, colour_topic, depth_topic, calib_source, pose_source, rectifier.intrinsics,
                             options.out, notes)
