"""Differentiable 3D Gaussian rasterizer: a fast CPU path (numba), a pure-torch tiled
compositor, and gsplat on CUDA. See ``design.md`` beside this file.

    from lmgs.render import rasterize
    out = rasterize(means, quats, log_scales, opacity_logits, colors, camera, background)
"""

from lmgs.render.rasterize import BACKENDS, Backend, RasterResult, rasterize

__all__ = ["BACKENDS", "Backend", "RasterResult", "rasterize"]
