"""A small z-buffered triangle rasteriser (numba) with texture, shading, alpha and normals.

Pixel ``(x, y)`` is sampled at its centre ``(x + 0.5, y + 0.5)``; vertex positions are in
the continuous pixel coordinates of :meth:`lmgs.types.Camera.project`. Attributes are
interpolated perspective-correctly (barycentrics divided by camera depth). Each pixel is
independent, so the result does not depend on thread scheduling.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, fastmath=False)
def _sample(tex, u, v):
    h, w = tex.shape[0], tex.shape[1]
    x = u - 0.5
    y = v - 0.5
    x0 = int(np.floor(x))
    y0 = int(np.floor(y))
    fx = x - x0
    fy = y - y0
    x0c = min(max(x0, 0), w - 1)
    x1c = min(max(x0 + 1, 0), w - 1)
    y0c = min(max(y0, 0), h - 1)
    y1c = min(max(y0 + 1, 0), h - 1)
    out = np.empty(3, np.float32)
    for c in range(3):
        a = tex[y0c, x0c, c] * (1 - fx) + tex[y0c, x1c, c] * fx
        b = tex[y1c, x0c, c] * (1 - fx) + tex[y1c, x1c, c] * fx
        out[c] = a * (1 - fy) + b * fy
    return out


@njit(cache=True, fastmath=False)
def rasterize(xy, z, uv, attr, faces, tex, height, width, want_rgb):
    """Rasterise triangles.

    Args:
        xy: ``[V, 2]`` float64 pixel positions.
        z: ``[V]`` float64 camera depth (> 0).
        uv: ``[V, 2]`` float64 texture positions (texture pixels, continuous).
        attr: ``[V, A]`` float64 attributes: column 0 shade (multiplies the texture),
            column 1 alpha, then any others (normals...).
        faces: ``[F, 3]`` int32.
        tex: ``[Ht, Wt, 3]`` float32 texture.
        height, width: image size.
        want_rgb: sample the texture (False: geometry only).

    Returns:
        rgb ``[H, W, 3]`` float32 (shaded texture, not premultiplied), attributes
        ``[H, W, A]`` float32, depth ``[H, W]`` float64 (``inf`` where empty), face index
        ``[H, W]`` int32 (-1 where empty).
    """
    na = attr.shape[1]
    rgb = np.zeros((height, width, 3), np.float32)
    out = np.zeros((height, width, na), np.float32)
    zbuf = np.full((height, width), np.inf)
    fid = np.full((height, width), -1, np.int32)
    for f in range(faces.shape[0]):
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        if z[i0] <= 1e-6 or z[i1] <= 1e-6 or z[i2] <= 1e-6:
            continue
        x0, y0 = xy[i0, 0], xy[i0, 1]
        x1, y1 = xy[i1, 0], xy[i1, 1]
        x2, y2 = xy[i2, 0], xy[i2, 1]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-12:
            continue
        xmin = max(int(np.floor(min(x0, min(x1, x2)) - 0.5)), 0)
        xmax = min(int(np.ceil(max(x0, max(x1, x2)) - 0.5)), width - 1)
        ymin = max(int(np.floor(min(y0, min(y1, y2)) - 0.5)), 0)
        ymax = min(int(np.ceil(max(y0, max(y1, y2)) - 0.5)), height - 1)
        if xmin > xmax or ymin > ymax:
            continue
        inv_area = 1.0 / area
        iz0, iz1, iz2 = 1.0 / z[i0], 1.0 / z[i1], 1.0 / z[i2]
        for py in range(ymin, ymax + 1):
            cy = py + 0.5
            for px in range(xmin, xmax + 1):
                cx = px + 0.5
                b0 = ((x1 - cx) * (y2 - cy) - (x2 - cx) * (y1 - cy)) * inv_area
                b1 = ((x2 - cx) * (y0 - cy) - (x0 - cx) * (y2 - cy)) * inv_area
                b2 = 1.0 - b0 - b1
                if b0 < -1e-9 or b1 < -1e-9 or b2 < -1e-9:
                    continue
                w0, w1, w2 = b0 * iz0, b1 * iz1, b2 * iz2
                ws = w0 + w1 + w2
                depth = 1.0 / ws
                if depth >= zbuf[py, px]:
                    continue
                zbuf[py, px] = depth
                fid[py, px] = f
                w0 /= ws
                w1 /= ws
                w2 /= ws
                for a in range(na):
                    out[py, px, a] = w0 * attr[i0, a] + w1 * attr[i1, a] + w2 * attr[i2, a]
                if want_rgb:
                    u = w0 * uv[i0, 0] + w1 * uv[i1, 0] + w2 * uv[i2, 0]
                    v = w0 * uv[i0, 1] + w1 * uv[i1, 1] + w2 * uv[i2, 1]
                    s = _sample(tex, u, v)
                    sh = out[py, px, 0]
                    for c in range(3):
                        rgb[py, px, c] = s[c] * sh
    return rgb, out, zbuf, fid


def downsample(img: np.ndarray, k: int) -> np.ndarray:
    """Box-filter an ``[kH, kW, ...]`` image by ``k`` (supersampling resolve)."""
    if k == 1:
        return img
    h, w = img.shape[0] // k, img.shape[1] // k
    return img.reshape(h, k, w, k, *img.shape[2:]).mean(axis=(1, 3))
