"""The MR image (paper Eq. 1): ``m_t = d_t ⊙ r_t + (1 − d_t) ⊙ v_t`` and the mask d_t from depths.

``d_t`` is 1 where the MR image shows the real image and 0 where it shows the virtual one: a pixel is
virtual when a virtual agent is hit there *and* is nearer than the real surface (camera-space z in
metres), so an agent behind a real box is hidden. Images are H×W×3 float32 in [0, 1]. No ROS: numpy, and
OpenCV for the JPEG of :func:`jpeg_mr_loss`.
"""

from __future__ import annotations

import numpy as np

from gsrmr_common.jpeg import decode_jpeg, encode_jpeg
from gsrmr_common.metrics import image_quality


def compose_mask(virtual_depth_m: np.ndarray, real_depth_m: np.ndarray) -> np.ndarray:
    """d_t: 1.0 where the real surface is nearer than (or no) virtual agent, 0.0 where an agent shows.

    Real depth +inf, NaN or ≤ 0 means "no real surface" (0 is the no-depth value of depth PNGs).
    """
    real = np.where(np.isfinite(real_depth_m) & (real_depth_m > 0), real_depth_m, np.inf)
    return np.where(np.isfinite(virtual_depth_m) & (virtual_depth_m < real), 0.0, 1.0).astype(np.float32)


def mr_image(real: np.ndarray, virtual: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The MR image m_t = d ⊙ r + (1 − d) ⊙ v (paper Eq. 1); H×W×3 float32."""
    d = np.asarray(mask, np.float32)[..., None]
    return (d * np.asarray(real, np.float32) + (1.0 - d) * np.asarray(virtual, np.float32)).astype(np.float32)


def jpeg_mr_loss(frame_u8: np.ndarray, virtual: np.ndarray, mask: np.ndarray, jpeg_quality: int) -> float:
    """MR loss an *image* slot leaves: the composite from the camera frame's JPEG at ``jpeg_quality`` (what
    the robot uploads), rounded to 8 bit as published, against the composite from the frame itself.
    ``frame_u8``: H×W×3 uint8 RGB; ``virtual``, ``mask`` as in :func:`mr_image`."""
    truth = mr_image(frame_u8.astype(np.float32) / 255.0, virtual, mask)
    jpeg = decode_jpeg(encode_jpeg(np.ascontiguousarray(frame_u8), int(jpeg_quality)))
    composite = mr_image(jpeg.astype(np.float32) / 255.0, virtual, mask)
    published = np.clip(np.rint(composite * 255.0), 0, 255).astype(np.float32) / 255.0
    return float(image_quality(truth, published)["loss"])
