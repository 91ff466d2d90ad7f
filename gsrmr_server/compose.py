"""The server's per-slot MR pipeline (pure): r̂_t from the upload or Φ(s_t), then m̂_t = d·r̂ + (1 − d)·v.

:class:`MRComposer` picks r̂_t (the sources: :class:`~gsrmr_common.wire.RealSource`; an uploaded JPEG whose
header lies about its size is refused before decoding). The GS render is made in every slot: its depth is the real
depth the virtual view is occluded against (d_t), and in image slots it gives the GS loss L_t, the MR loss between
the MR image with the uploaded image and the one with Φ(s_t): the sample the scheduler's loss map learns from.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
import time

import cv2
import numpy as np

from gsrmr_common.camera import Camera, CameraMount, Intrinsics, camera_from_pose
from gsrmr_common.jpeg import ImageRejected, decode_jpeg, jpeg_header
from gsrmr_common.metrics import mr_loss
from gsrmr_common.wire import MAX_IMAGE_PIXELS, PoseKey, RealSource, UplinkFault
from gsrmr_server.mr.blend import mr_image
from gsrmr_server.mr.content import VirtualViewSource
from gsrmr_server.uplink import SlotUploads
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import RenderOutput, render


@dataclass
class ComposedSlot:
    """Result of one slot: the MR image and how it was made."""

    slot: int
    mr: np.ndarray  # H×W×3 float32 in [0, 1]
    real_estimate: np.ndarray  # r̂_t
    virtual: np.ndarray  # v_t
    mask: np.ndarray  # d_t, 1 = real
    source: RealSource  # where r̂_t came from
    pose: PoseKey | None
    gs_loss: float | None = None  # measured L_t (image slots only)
    faults: list[UplinkFault] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)
    gs_mr: np.ndarray | None = None  # the composite from the GS render (= mr in render/fallback slots)


class MRComposer:
    """Builds m̂_t for each slot from the uploads, the GS model and a virtual-view source."""

    def __init__(self, model: GaussianModel, virtual: VirtualViewSource, intrinsics: Intrinsics,
                 mount: CameraMount, background_rgb: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 render_threads: int | None = None) -> None:
        self.model = model
        self.render_threads = render_threads  # numba threads of the GS render (None = all)
        self.virtual = virtual
        self.intrinsics = intrinsics
        self.mount = mount
        self.background_rgb = np.asarray(background_rgb, np.float32)
        self._caster: ThreadPoolExecutor | None = None  # casts the virtual view beside the GS render

    def _cast_beside(self, camera: Camera, time_s: float) -> Future | None:
        """Start the virtual view's ray cast on a worker thread (it needs no real depth, and its kernel releases
        the GIL), so it runs while this thread renders Φ; None when the source cannot be split (cast, occlude)."""
        if not (hasattr(self.virtual, "cast") and hasattr(self.virtual, "occlude")):
            return None
        if self._caster is None:
            self._caster = ThreadPoolExecutor(max_workers=1, thread_name_prefix="virtual-cast")
        return self._caster.submit(self.virtual.cast, camera, time_s=time_s)

    def warm_up(self, model: GaussianModel) -> GaussianModel:
        """Render ``model`` once with this composer's view, content and intrinsics (one thread, on the caller's
        thread: a model swap's loader), so the first slot composed with it pays no first-touch cost."""
        probe = MRComposer(model, self.virtual, self.intrinsics, self.mount,
                           tuple(float(c) for c in self.background_rgb),  # type: ignore[arg-type]
                           render_threads=1)
        probe.compose(SlotUploads(0), PoseKey(0, 0.0, 0.0, 0.0), 0.0, measure_loss=False)
        return model

    def compose(self, uploads: SlotUploads, best_pose: PoseKey | None, time_s: float,
                measure_loss: bool = True, render_scale: float = 1.0) -> ComposedSlot:
        """Compose slot ``uploads.slot``; never raises on bad uploads (they become faults). ``render_scale`` < 1
        renders Φ at that fraction of the width and height and enlarges it (colour bilinear, depth and opacity
        nearest), for a slot short of time (:mod:`gsrmr_server.compose_levels`); the virtual view stays full size."""
        t0 = time.perf_counter()
        faults = list(uploads.faults)
        k = self.intrinsics
        image = None
        if uploads.jpeg is not None:
            try:
                image = decode_jpeg(uploads.jpeg, expected_shape=(k.height, k.width))
            except ImageRejected:
                faults.append(refusal_fault(uploads.jpeg, k.width, k.height))
        t_decode = time.perf_counter()
        pose = uploads.key if uploads.key is not None else best_pose
        if pose is None:
            r_hat = np.broadcast_to(self.background_rgb, (k.height, k.width, 3)).astype(np.float32)
            if image is not None:
                r_hat = image.astype(np.float32) / 255.0
            v = np.zeros((k.height, k.width, 3), np.float32)
            d = np.ones((k.height, k.width), np.float32)
            return ComposedSlot(uploads.slot, r_hat.copy(), r_hat, v, d,
                                RealSource.IMAGE if image is not None else RealSource.NONE,
                                None, None, faults, {"total": 1e3 * (time.perf_counter() - t0)})
        camera = camera_from_pose(pose.a_m, pose.b_m, pose.theta_rad, self.mount, k)
        cast = self._cast_beside(camera, time_s)
        cpu0 = time.thread_time()
        if render_scale < 1.0:
            small = k.scaled(max(1, round(k.width * render_scale)), max(1, round(k.height * render_scale)))
            out = enlarged(render(self.model, camera_from_pose(pose.a_m, pose.b_m, pose.theta_rad, self.mount, small),
                                  self.background_rgb, threads=self.render_threads), k.width, k.height)
        else:
            out = render(self.model, camera, self.background_rgb, threads=self.render_threads)
        t_render = time.perf_counter()
        render_cpu_ms = 1e3 * (time.thread_time() - cpu0)  # this thread's CPU (wall − this = time waited)
        real_depth = np.where(out.alpha > 0.5, out.depth, np.inf).astype(np.float32)
        if cast is not None:  # "virtual" is then what is left of the cast after the render, plus the occlusion
            v, d = self.virtual.occlude(camera, cast.result(), real_depth)
        else:
            v, d = self.virtual.render(camera, time_s=time_s, real_depth_m=real_depth)
        gs_mr = mr_image(out.rgb, v, d)
        t_virtual = time.perf_counter()
        gs_loss = None
        if image is not None:
            r_hat = image.astype(np.float32) / 255.0
            mr = mr_image(r_hat, v, d)
            source = RealSource.IMAGE
            if measure_loss and uploads.key is not None:
                gs_loss = mr_loss(mr, gs_mr)
        else:
            r_hat, mr = out.rgb, gs_mr
            source = RealSource.RENDER if uploads.key is not None and uploads.jpeg is None else RealSource.FALLBACK
        t_end = time.perf_counter()
        timings = {"decode": 1e3 * (t_decode - t0), "render": 1e3 * (t_render - t_decode),
                   "render_cpu": render_cpu_ms, "virtual": 1e3 * (t_virtual - t_render),
                   "loss": 1e3 * (t_end - t_virtual),
                   "total": 1e3 * (t_end - t0)}
        return ComposedSlot(uploads.slot, mr, r_hat, v, d, source, pose, gs_loss, faults, timings, gs_mr)


def enlarged(out: RenderOutput, width_px: int, height_px: int) -> RenderOutput:
    """A render made at a fraction of the size, enlarged to ``width_px`` × ``height_px``: colour bilinear (pixel
    centres kept, as ``cv2.resize`` maps them), depth and opacity nearest (an edge's depth is not blended)."""
    size = (int(width_px), int(height_px))
    return replace(out, rgb=cv2.resize(out.rgb, size, interpolation=cv2.INTER_LINEAR),
                   alpha=cv2.resize(out.alpha, size, interpolation=cv2.INTER_NEAREST),
                   depth=cv2.resize(out.depth, size, interpolation=cv2.INTER_NEAREST))


def refusal_fault(jpeg: bytes, width_px: int, height_px: int) -> UplinkFault:
    """Fault name for a refused upload: ``oversized_header`` (frame header claims more than
    :data:`~gsrmr_common.wire.MAX_IMAGE_PIXELS`), ``wrong_size`` (a readable header of another size than
    ``width_px`` × ``height_px``) or ``corrupt_image`` (unreadable header, truncated or corrupt data)."""
    try:
        header = jpeg_header(jpeg)
    except ImageRejected:
        return UplinkFault.CORRUPT_IMAGE
    if header.width * header.height > MAX_IMAGE_PIXELS:
        return UplinkFault.OVERSIZED_HEADER
    if (header.width, header.height) != (width_px, height_px):
        return UplinkFault.WRONG_SIZE
    return UplinkFault.CORRUPT_IMAGE


def to_u8(img: np.ndarray) -> np.ndarray:
    """float [0, 1] image → uint8 (rounded)."""
    return np.clip(np.round(np.asarray(img, np.float32) * 255.0), 0, 255).astype(np.uint8)
