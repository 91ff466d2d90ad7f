"""CPU Gaussian-splatting engine: model and .ply IO, EWA projection, numba tile rasterizer, training.

Public entry points: :class:`~gsrmr_server.splatting.model.GaussianModel`,
:func:`~gsrmr_server.splatting.render.render` and :class:`~gsrmr_server.splatting.train.Trainer`.
Conventions (OpenCV camera axes, pixel centres at +0.5, 3DGS compositing) are described in
``docs/splatting.md``.
"""

from gsrmr_server.splatting.model import GaussianModel
from gsrmr_server.splatting.render import RenderOutput, render

__all__ = ["GaussianModel", "RenderOutput", "render"]
