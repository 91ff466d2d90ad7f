"""A pure TF buffer: a tree of frames whose edges are static transforms or time series, looked up at any stamp.

What ``tf2``'s buffer does for a recorded bag, without ROS. An edge is a :class:`~gsrmr_common.tf_tree.Transform`
(its convention); stamps are integer nanoseconds; :meth:`TfBuffer.lookup` returns ``target_from_source``, e.g.
``lookup("map", "camera_optical_frame", t)`` is the camera→world matrix at ``t``. Interpolation (linear, slerp),
``out_of_range`` and ``gap``: docs/dataset_tool.md, "Where the camera was". Besides: a frame has one parent (the
first edge seen for a child decides; samples naming another parent are ignored and counted,
:attr:`TfBuffer.parent_conflicts`), a static transform of an edge wins over its samples, and a repeated sample
stamp keeps the last sample added.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from gsrmr_common.tf_tree import Transform, rotation_matrix

NS_PER_S = 1_000_000_000
#: Two samples of an edge this close (translation [m], rotation [rad]) move nothing between them: an edge whose
#: samples all agree is constant (a fixed transform sent on /tf, as a ROS 1 static_transform_publisher or an idle
#: localizer does) and looked up as a static one; a bracket whose two samples agree counts no gap.
STILL_M = 1e-3
STILL_RAD = math.radians(0.1)
NO_TF_PATH = "no_tf_path"
OUT_OF_RANGE = "out_of_range"
GAP = "gap"


def strip_frame(name: str) -> str:
    """A frame name as tf2 keys it: without leading ``/`` (``"/base_link"`` → ``"base_link"``)."""
    return str(name).lstrip("/")


def slerp(q0: np.ndarray, q1: np.ndarray, fraction: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (x, y, z, w) along the shorter arc: ``fraction`` 0
    gives ``q0``, 1 gives ``q1`` (or ``-q1``, the same rotation). Returns a unit quaternion."""
    a = np.asarray(q0, dtype=np.float64) / np.linalg.norm(q0)
    b = np.asarray(q1, dtype=np.float64) / np.linalg.norm(q1)
    dot = float(a @ b)
    if dot < 0.0:
        b, dot = -b, -dot
    if dot > 0.9999995:  # nearly the same rotation: the chord is the arc to 1e-13
        out = a + fraction * (b - a)
    else:
        theta = math.acos(min(1.0, dot))
        sin_theta = math.sin(theta)
        out = (math.sin((1.0 - fraction) * theta) * a + math.sin(fraction * theta) * b) / sin_theta
    return out / np.linalg.norm(out)


def _matrix(translation: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rotation_matrix(tuple(float(v) for v in quaternion))
    out[:3, 3] = translation
    return out


def invert(matrix: np.ndarray) -> np.ndarray:
    """Inverse of a 4×4 rigid transform."""
    rot = matrix[:3, :3]
    out = np.eye(4)
    out[:3, :3] = rot.T
    out[:3, 3] = -rot.T @ matrix[:3, 3]
    return out


class TfLookupError(LookupError):
    """A lookup that cannot be answered: ``reason`` is :data:`NO_TF_PATH`, :data:`OUT_OF_RANGE` or :data:`GAP`;
    ``widest_gap_s`` the widest bracket seen on the chain (for a gap), the message says which edge and why."""

    def __init__(self, reason: str, message: str, widest_gap_s: float | None = None) -> None:
        super().__init__(message)
        self.reason = reason
        self.widest_gap_s = widest_gap_s


@dataclass
class _Edge:
    """One edge parent → child: a static transform, or samples (sorted on first use)."""

    parent: str
    static: np.ndarray | None = None  # 4×4
    _stamps: list[int] = field(default_factory=list)
    _translations: list[tuple[float, float, float]] = field(default_factory=list)
    _rotations: list[tuple[float, float, float, float]] = field(default_factory=list)
    _sorted: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    _constant: tuple[np.ndarray | None] | None = None  # (the constant value or None,), once computed

    def add(self, stamp_ns: int, transform: Transform) -> None:
        self._stamps.append(int(stamp_ns))
        self._translations.append(tuple(float(v) for v in transform.translation))
        self._rotations.append(tuple(float(v) for v in transform.rotation))
        self._sorted = None
        self._constant = None

    @property
    def is_static(self) -> bool:
        """A static transform, or samples (two or more) that all agree: the edge moves nothing."""
        return self.static is not None or self.constant() is not None

    def constant(self) -> np.ndarray | None:
        """The 4×4 value of an edge whose samples (two or more) all agree with the first, else ``None``."""
        if self.static is not None or len(self._stamps) < 2:
            return None
        if self._constant is None:
            stamps, trans, rots = self.series()
            moved_m = np.linalg.norm(trans - trans[0], axis=1)
            turned_rad = 2.0 * np.arccos(np.minimum(1.0, np.abs(rots @ rots[0])))
            still = len(stamps) >= 2 and bool(np.all(moved_m <= STILL_M) and np.all(turned_rad <= STILL_RAD))
            self._constant = (_matrix(trans[0], rots[0]) if still else None,)
        return self._constant[0]

    def series(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(stamps int64 [N], translations [N×3], unit quaternions [N×4]) sorted by stamp, last sample per stamp."""
        if self._sorted is None:
            stamps = np.asarray(self._stamps, dtype=np.int64)
            order = np.argsort(stamps, kind="stable")
            stamps = stamps[order]
            keep = np.ones(len(stamps), dtype=bool)
            keep[:-1] = stamps[1:] != stamps[:-1]  # of equal stamps, the last one added
            trans = np.asarray(self._translations, dtype=np.float64).reshape(-1, 3)[order][keep]
            rots = np.asarray(self._rotations, dtype=np.float64).reshape(-1, 4)[order][keep]
            rots /= np.linalg.norm(rots, axis=1, keepdims=True)
            self._sorted = (stamps[keep], trans, rots)
        return self._sorted

    def time_range_ns(self) -> tuple[int, int] | None:
        """[first, last] sample stamp of a moving edge; ``None`` for a static or constant one or an edge without
        samples."""
        if self.is_static or not self._stamps:
            return None
        stamps = self.series()[0]
        return int(stamps[0]), int(stamps[-1])


@dataclass(frozen=True)
class ChainLookup:
    """A lookup's answer: ``target_from_source`` (4×4, metres), the widest bracket on the chain's moving edges
    at the stamp (``widest_gap_s``, seconds; 0 when the chain is static or every stamp hit a sample) and the
    moving edges (parent, child) the chain crosses."""

    target_from_source: np.ndarray
    widest_gap_s: float
    moving_edges: tuple[tuple[str, str], ...]


class TfBuffer:
    """Frames and their edges from ``/tf`` and ``/tf_static`` (module docstring for the rules)."""

    def __init__(self) -> None:
        self._edges: dict[str, _Edge] = {}  # child → edge from its parent
        self.parent_conflicts: dict[str, set[str]] = {}  # child → parents ignored for it
        self.ignored_samples = 0

    # ----------------------------------------------------------------------------------------------- filling

    def _edge_for(self, parent: str, child: str) -> _Edge | None:
        parent, child = strip_frame(parent), strip_frame(child)
        if not parent or not child or parent == child:
            raise ValueError(f"TF edge {parent!r} → {child!r}: frames must be non-empty and distinct")
        edge = self._edges.get(child)
        if edge is None:
            edge = self._edges[child] = _Edge(parent)
        elif edge.parent != parent:
            self.parent_conflicts.setdefault(child, set()).add(parent)
            self.ignored_samples += 1
            return None
        return edge

    def set_static(self, parent: str, child: str, transform: Transform) -> None:
        """The static edge ``parent → child`` (a later call for the same edge replaces it)."""
        edge = self._edge_for(parent, child)
        if edge is not None:
            edge.static = _matrix(np.asarray(transform.translation, dtype=np.float64),
                                  np.asarray(transform.rotation, dtype=np.float64))

    def add_sample(self, parent: str, child: str, stamp_ns: int, transform: Transform) -> None:
        """One sample of the moving edge ``parent → child`` at ``stamp_ns``."""
        edge = self._edge_for(parent, child)
        if edge is not None:
            edge.add(stamp_ns, transform)

    def remove_edge_into(self, child: str) -> bool:
        """Forget the edge into ``child`` (static or moving); whether there was one."""
        return self._edges.pop(strip_frame(child), None) is not None

    # ------------------------------------------------------------------------------------------- inspection

    def parents(self) -> dict[str, str | None]:
        """Every frame → its parent (``None`` for a root), sorted by frame name."""
        out: dict[str, str | None] = {child: edge.parent for child, edge in self._edges.items()}
        for edge in self._edges.values():
            out.setdefault(edge.parent, None)
        return dict(sorted(out.items()))

    def has_frame(self, frame: str) -> bool:
        """Whether ``frame`` is in the tree (as a child or a parent)."""
        return strip_frame(frame) in self.parents()

    def is_static_edge(self, child: str) -> bool:
        """Whether the edge into ``child`` is static (``False`` for a root or unknown frame)."""
        edge = self._edges.get(strip_frame(child))
        return edge is not None and edge.is_static

    def describe_tree(self) -> str:
        """One line: every frame with its parent, static or moving edges marked — for error messages."""
        parts = []
        for frame, parent in self.parents().items():
            if parent is None:
                parts.append(f"{frame} (root)")
            else:
                kind = "static" if self._edges[frame].is_static else "moving"
                parts.append(f"{frame} (parent {parent}, {kind})")
        return ", ".join(parts) if parts else "no frames at all"

    def _ancestors(self, frame: str) -> list[str]:
        path, seen = [frame], {frame}
        while (edge := self._edges.get(path[-1])) is not None:
            if edge.parent in seen:  # a loop (bad data): stop at it
                break
            path.append(edge.parent)
            seen.add(edge.parent)
        return path

    def chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """The frames from ``source`` up to the common ancestor and from ``target`` up to it (both lists end
        with the ancestor). :class:`TfLookupError` (:data:`NO_TF_PATH`) when the frames are not connected."""
        target, source = strip_frame(target), strip_frame(source)
        known = self.parents()
        for frame in (target, source):
            if frame not in known:
                raise TfLookupError(NO_TF_PATH, f"frame {frame!r} is not in the TF tree ({self.describe_tree()})")
        up_source, up_target = self._ancestors(source), self._ancestors(target)
        on_target = set(up_target)
        for i, frame in enumerate(up_source):
            if frame in on_target:
                return up_source[: i + 1], up_target[: up_target.index(frame) + 1]
        raise TfLookupError(NO_TF_PATH, f"no TF path between {target!r} and {source!r}: {source} leads up to "
                                        f"{up_source[-1]}, {target} to {up_target[-1]} ({self.describe_tree()})")

    def moving_edges(self, target: str, source: str) -> list[tuple[str, str]]:
        """(parent, child) of every moving edge on the chain between the frames."""
        up_source, up_target = self.chain(target, source)
        return [(self._edges[c].parent, c) for c in (*up_source[:-1], *up_target[:-1])
                if not self._edges[c].is_static]

    def time_range_ns(self, target: str, source: str) -> tuple[int, int] | None:
        """The stamps a lookup between the frames can take: the intersection of the moving edges' sample ranges
        (``None`` when the chain is static; an empty intersection comes back with first > last)."""
        ranges = [self._edges[c].time_range_ns() for _p, c in self.moving_edges(target, source)]
        ranges = [r for r in ranges if r is not None]
        if not ranges:
            return None
        return max(r[0] for r in ranges), min(r[1] for r in ranges)

    def edge_time_range_ns(self, child: str) -> tuple[int, int] | None:
        """[first, last] sample stamp of the moving edge into ``child`` (``None`` if static or unknown)."""
        edge = self._edges.get(strip_frame(child))
        return None if edge is None else edge.time_range_ns()

    # ----------------------------------------------------------------------------------------------- lookup

    def _edge_at(self, child: str, stamp_ns: int) -> tuple[np.ndarray, float]:
        """``parent_from_child`` of the edge into ``child`` at ``stamp_ns`` and its bracket length [s]."""
        edge = self._edges[child]
        if edge.static is not None:
            return edge.static, 0.0
        constant = edge.constant()
        if constant is not None:
            return constant, 0.0
        stamps, trans, rots = edge.series()
        if len(stamps) == 0 or stamp_ns < stamps[0] or stamp_ns > stamps[-1]:
            span = "no samples" if len(stamps) == 0 else \
                f"samples {stamps[0] / NS_PER_S:.6f}–{stamps[-1] / NS_PER_S:.6f} s"
            raise TfLookupError(OUT_OF_RANGE, f"stamp {stamp_ns / NS_PER_S:.6f} s is outside {edge.parent} → {child} "
                                              f"({span})")
        i = int(np.searchsorted(stamps, stamp_ns, side="right")) - 1
        if stamps[i] == stamp_ns:
            return _matrix(trans[i], rots[i]), 0.0
        t0, t1 = int(stamps[i]), int(stamps[i + 1])
        fraction = (stamp_ns - t0) / (t1 - t0)
        translation = trans[i] + fraction * (trans[i + 1] - trans[i])
        still = _agree(trans[i], rots[i], trans[i + 1], rots[i + 1])  # the bracket moves nothing: no gap
        return _matrix(translation, slerp(rots[i], rots[i + 1], fraction)), 0.0 if still else (t1 - t0) / NS_PER_S

    def lookup(self, target: str, source: str, stamp_ns: int, max_gap_s: float | None = None) -> ChainLookup:
        """``target_from_source`` at ``stamp_ns`` (module docstring). Raises :class:`TfLookupError` with reason
        :data:`NO_TF_PATH`, :data:`OUT_OF_RANGE` (a moving edge has no sample at or after / before the stamp) or,
        with ``max_gap_s``, :data:`GAP` (a bracket on a moving edge is longer than ``max_gap_s`` seconds)."""
        up_source, up_target = self.chain(target, source)
        widest = 0.0
        worst = ""
        moving: list[tuple[str, str]] = []
        halves = []
        for path in (up_source, up_target):
            ancestor_from_frame = np.eye(4)
            for child in reversed(path[:-1]):  # from the ancestor down to the frame
                edge_matrix, gap_s = self._edge_at(child, int(stamp_ns))
                ancestor_from_frame = ancestor_from_frame @ edge_matrix
                if not self._edges[child].is_static:
                    moving.append((self._edges[child].parent, child))
                    if gap_s > widest:
                        widest, worst = gap_s, f"{self._edges[child].parent} → {child}"
            halves.append(ancestor_from_frame)
        if max_gap_s is not None and widest > max_gap_s:
            raise TfLookupError(GAP, f"at {stamp_ns / NS_PER_S:.6f} s the samples of {worst} are {widest:.3f} s "
                                     f"apart (more than {max_gap_s:g} s)", widest)
        return ChainLookup(invert(halves[1]) @ halves[0], widest, tuple(moving))


def _agree(t0: np.ndarray, q0: np.ndarray, t1: np.ndarray, q1: np.ndarray) -> bool:
    """Whether two samples (translation [m], unit quaternion x, y, z, w) are within :data:`STILL_M` and
    :data:`STILL_RAD` of each other."""
    dot = min(1.0, abs(float(np.dot(q0, q1))))
    return float(np.linalg.norm(np.asarray(t1) - np.asarray(t0))) <= STILL_M and 2.0 * math.acos(dot) <= STILL_RAD


def rotation_angle_rad(rotation: np.ndarray) -> float:
    """The angle [rad, 0…π] of a 3×3 rotation matrix (e.g. between two camera orientations, ``Ra.T @ Rb``)."""
    cos = (float(np.trace(rotation)) - 1.0) / 2.0
    sin = float(np.linalg.norm([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0],
                                rotation[1, 0] - rotation[0, 1]])) / 2.0
    return math.atan2(sin, cos)
