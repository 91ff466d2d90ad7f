"""The live server's slot core run offline over a recorded round: one composition/evaluation pipeline for
the live server, the survey (seed loss map) and the experiments.

:class:`OfflineServer` feeds :meth:`gsrmr_server.slot_core.ServerCore.process` what the robot would have uploaded
for a delivery (``image``, ``key`` or ``none``) and scores the published 8-bit m̂ against the true m with
:func:`gsrmr_server.scoring.score_slot`, as ``gsrmr-demo``'s scorer does: docs/experiments.md, "Data pipeline",
item 3, and docs/architecture.md, "One pipeline each".
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.wire import PoseKey
from gsrmr_scheduler.problem import IMAGE, KEY, NONE
from gsrmr_server.mr.blend import mr_image
from gsrmr_server.scoring import score_slot
from gsrmr_server.server_params import ServerParameters
from gsrmr_server.slot_core import SlotOutcome, build_server_core
from gsrmr_server.slot_row import SlotScore
from gsrmr_server.uplink import SlotUploads, UplinkAssembler
from gsrmr_sim.world.recorder import Round2Record
from gsrmr_splat.model import GaussianModel

#: Which pose a key carries: the one the robot reports (odometry) or the true one (the paper's L_t).
TRUE, REPORTED = "true", "reported"


@dataclass(frozen=True)
class SlotQuality:
    """The scored m̂ of one slot: loss (3DGS image loss), PSNR (dB) and SSIM against the true m."""

    loss: float
    psnr_db: float
    ssim: float


class OfflineServer:
    """:class:`~gsrmr_server.slot_core.ServerCore` over a recorded round (see the module docstring)."""

    def __init__(self, record: Round2Record, model: GaussianModel, *, mr_content: str,
                 background_rgb: tuple[float, float, float], jpeg_quality: int,
                 reported_poses: np.ndarray | None = None, render_threads: int = 0) -> None:
        """``jpeg_quality``: the robot's JPEG quality for image slots; ``reported_poses``: T×3 (a_m, b_m,
        theta_rad) in ``map`` the robot reports (None: the true poses); ``render_threads`` 0 = every core.
        The core is :func:`~gsrmr_server.slot_core.build_server_core`'s, as the server node builds it."""
        self.record = record
        self.jpeg_quality = int(jpeg_quality)
        true = record.poses
        self.true_poses = true
        self.reported = true if reported_poses is None else np.asarray(reported_poses, np.float64)
        if self.reported.shape != true.shape:
            raise ValueError(f"reported poses are {self.reported.shape}, the record has {true.shape}")
        params = ServerParameters(model_path="(in memory)", mr_content=mr_content, background_rgb=tuple(background_rgb),
                                  measure_loss=False, render_threads=render_threads, camera_mount=record.mount)
        self.core = build_server_core(params, model, record.intrinsics, warm_up=False)
        self._times = record.times_s
        self._cache: dict[tuple, SlotQuality] = {}
        self._frame: tuple[int, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.record)

    def key(self, slot: int, pose: str = REPORTED) -> PoseKey:
        """The pose key of ``slot`` (the reported or the true pose)."""
        a, b, th = (self.reported if pose == REPORTED else self.true_poses)[slot]
        return PoseKey(slot, float(a), float(b), float(th))

    def frame_u8(self, t: int) -> np.ndarray:
        """The true camera frame r_t (H×W×3 uint8), as the camera published it."""
        if self._frame is None or self._frame[0] != t:
            rec = self.record[t]
            self._frame = (t, np.clip(np.rint(rec.image * 255.0), 0, 255).astype(np.uint8))
        return self._frame[1]

    def outcome(self, uploads: SlotUploads, best_pose: PoseKey | None) -> SlotOutcome:
        """One slot composed by the live core (``outcome.mr_u8``: m̂ as published)."""
        t = uploads.slot
        return self.core.process(uploads, best_pose, time_s=float(self._times[t]), stamp_s=float(self._times[t]))

    def score(self, outcome: SlotOutcome) -> SlotScore:
        """A composed slot's scores against the true frame of its slot (the deployment's scoring library)."""
        return score_slot(outcome.composed, outcome.mr_u8, self.frame_u8(outcome.composed.slot))

    def _scored(self, uploads: SlotUploads, best_pose: PoseKey | None) -> SlotQuality:
        """:meth:`outcome`'s scores, cached per (slot, what the server composes from)."""
        shown = uploads.key if uploads.key is not None else best_pose
        k = (uploads.slot, uploads.jpeg is not None,
             None if shown is None else (round(shown.a_m, 9), round(shown.b_m, 9), round(shown.theta_rad, 9)))
        if k not in self._cache:
            q = self.score(self.outcome(uploads, best_pose))
            if not q.scored:
                raise ValueError(f"slot {uploads.slot}: the recorded frame does not match the camera")
            self._cache[k] = SlotQuality(float(q.loss), float(q.psnr_db), float(q.ssim))  # type: ignore[arg-type]
        return self._cache[k]

    def quality(self, t: int, delivery: str, pose: str = REPORTED) -> SlotQuality:
        """Slot t on its own (no earlier slots: ``none`` shows the background) at the reported/true pose."""
        return self.evaluate([NONE] * t + [delivery], pose=pose, first=t)[0]

    def _replay(self, delivered: list[str], pose: str, first: int) -> Iterator[tuple[SlotUploads, PoseKey | None]]:
        """Slot by slot through the live uplink path (:class:`~gsrmr_server.uplink.UplinkAssembler`: keys
        admitted as they arrive, a slot without a key composed at its ``best_pose``): (uploads, fallback pose)
        of slots ``first`` … ``len(delivered) − 1``."""
        if len(delivered) > len(self):
            raise ValueError(f"delivered has {len(delivered)} slots, the record {len(self)}")
        uplink = UplinkAssembler()
        for t, d in enumerate(delivered):
            if d not in (IMAGE, KEY, NONE):
                raise ValueError(f"slot {t}: unknown delivery {d!r}")
            if d in (IMAGE, KEY):
                uplink.on_key(self.key(t, pose), t, 0)
            if d == IMAGE and t >= first:
                uplink.on_image(t, encode_jpeg(self.frame_u8(t), self.jpeg_quality), t, 0)
            best = uplink.best_pose(t)
            uploads = uplink.take(t, d == IMAGE)
            if t >= first:
                yield uploads, best

    def evaluate(self, delivered: list[str], pose: str = REPORTED, first: int = 0) -> list[SlotQuality]:
        """Every slot's scores under a delivery pattern (slots ``first`` … ``len(delivered) − 1``; the
        earlier ones only feed the uplink path)."""
        return [self._scored(u, best) for u, best in self._replay(delivered, pose, first)]

    def images(self, delivered: list[str], t: int, pose: str = REPORTED) -> tuple[np.ndarray, np.ndarray]:
        """(m_t, m̂_t) of slot t under ``delivered`` (H×W×3 float in [0, 1]; m̂ as published, 8 bit)."""
        uploads, best = next(self._replay(list(delivered[: t + 1]), pose, t))
        out = self.outcome(uploads, best)
        c = out.composed
        truth = mr_image(self.frame_u8(t).astype(np.float32) / 255.0, c.virtual, c.mask)
        return truth, out.mr_u8.astype(np.float32) / 255.0
