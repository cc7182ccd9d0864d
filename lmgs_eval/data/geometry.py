"""Depth and normal priors: a head-sized ellipsoid posed with the fitted head, seen by each camera.

The 3DGS methods place their first Gaussians by back-projecting the head's pixels with a depth
map, and lmgs's Geometry Regularizer compares rendered depth and normals with the maps. A real
video has neither. This writes the coarsest geometry the fit supports: an ellipsoid in the
head's frame (centred behind the nose bridge, semi-axes from the jaw width, the proportions
the bundled heads use), ray-cast per pixel of the head mask. Hair and ears reach beyond the
ellipsoid's outline; their pixels take the sheet through that outline (facing the camera), so
the whole head mask has a depth and the methods place Gaussians on all of it. It has no nose,
lips or hair shape; it tells the methods where the head is and which way its surface faces, no
more. Where a face mesh is tracked (the ingest's), :func:`render_mesh` draws the face itself over
it, and :func:`meet_mesh` moves the ellipsoid so that the two meet at the face's outline.
"""

from __future__ import annotations

import numpy as np

DEPTH_SCALE = 10000.0  # depth PNG value = camera z (metres) x 10000, as the bundled subjects
# Semi-axes in jaw widths (x: across, y: up, z: front to back) and the front of the surface
# relative to the brows' depth: the bundled heads' ellipsoid, a little taller to take the hair.
AXES = (0.56, 0.85, 0.63)
# Depth of the ingest's face template (lmgs_eval.data.ingest.pose) relative to MEAN_FACE_DEPTH,
# and the relief the 3D landmarks derived for a plain folder get (lmgs_eval.data.complete).
# Small head turns cannot separate depth relief from rotation angle (a flatter face turned
# further projects alike), so the relief is a prior. At 1.0 the yaw of both bundled heads came out about twice the truth; at 1.5 the mean
# rotation error fell from 0.84 / 2.45 deg to 0.55 / 1.74 deg (astronaut / hopper, 256 px, 4 s),
# and on the real 8 s clip the yaw range from +-25 to +-20 deg (a visibly moderate turn).
RELIEF = 1.5


def head_ellipsoid(template: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre ``[3]`` and semi-axes ``[3]`` (world metres) for a fitted 68-point template."""
    jaw = float(np.linalg.norm(template[16] - template[0]))
    axes = np.asarray(AXES) * jaw
    front = float(template[17:27, 2].mean())  # the brows lie on the smooth front of the head
    centre = np.array([0.5 * (template[0, 0] + template[16, 0]), template[28, 1], front - axes[2]])
    return centre, axes


def render_prior(w2c: np.ndarray, focal: float, w: int, h: int, centre: np.ndarray, axes: np.ndarray,
                 mask: np.ndarray, *, cx: float | None = None, cy: float | None = None,
                 rim: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Depth ``[H, W]`` (camera z, 0 off the surface) and unit normals ``[H, W, 3]`` (OpenCV
    camera axes, facing the camera) of the ellipsoid, inside ``mask`` only.

    ``rim``: a pixel of the mask whose ray misses the ellipsoid (hair or ears beyond its outline)
    takes the point of its ray nearest the ellipsoid's centre, in the ellipsoid's own metric: the
    sheet through the outline, at the outline's depth, which meets the surface without a step
    there, and faces the camera along the ray (the sheet's own normal, so that the two maps
    agree). Without it such pixels stay 0."""
    ys, xs = np.nonzero(mask)
    depth = np.zeros((h, w), np.float32)
    normal = np.zeros((h, w, 3), np.float32)
    if len(ys) == 0:
        return depth, normal
    cx = w / 2 if cx is None else cx
    cy = h / 2 if cy is None else cy
    f32 = np.float32
    d_cam = np.empty((len(xs), 3), f32)
    d_cam[:, 0] = (xs.astype(f32) + f32(0.5 - cx)) / f32(focal)
    d_cam[:, 1] = (ys.astype(f32) + f32(0.5 - cy)) / f32(focal)
    d_cam[:, 2] = 1.0
    R, t = w2c[:3, :3], w2c[:3, 3]
    o = -R.T @ t  # camera centre in the world
    d_s = d_cam @ (R / axes[None, :]).astype(f32)  # world ray directions, in the unit sphere's frame
    o_s = ((o - centre) / axes).astype(f32)
    a = np.einsum("ij,ij->i", d_s, d_s)
    b = 2 * (d_s @ o_s)
    c = f32(o_s @ o_s - 1.0)
    disc = b * b - 4 * a * c
    hit = disc > 0
    tt = np.where(hit, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), -b / (2 * a))  # camera z, since d_cam has z = 1
    sel = np.nonzero((tt > 0) & (hit | rim))[0]
    tt = tt[sel]
    p_s = o_s + tt[:, None] * d_s[sel]  # the hit on the unit sphere; its world normal is p_s / axes
    n_c = (p_s / axes[None, :].astype(f32)) @ R.T.astype(f32)
    n_c /= np.sqrt(np.einsum("ij,ij->i", n_c, n_c))[:, None]
    off = ~hit[sel]
    ray = d_cam[sel[off]]
    n_c[off] = -ray / np.sqrt(np.einsum("ij,ij->i", ray, ray))[:, None]
    depth[ys[sel], xs[sel]] = tt
    normal[ys[sel], xs[sel]] = n_c
    return depth, normal


def render_mesh(verts: np.ndarray, faces: np.ndarray, focal: float, w: int, h: int, *,
                cx: float | None = None, cy: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Depth ``[H, W]`` (camera z, 0 where no triangle) and unit normals ``[H, W, 3]`` (OpenCV
    camera axes, turned to face the camera) of a triangle mesh: at each pixel whose centre some
    triangle covers, the nearest such triangle (the z-buffered rasteriser the bundled heads are
    drawn with, :func:`lmgs_eval.data.raster.rasterize`).

    ``verts [V, 3]``: camera coordinates (OpenCV: x right, y down, z away); ``faces [F, 3]``:
    vertex indices. A triangle with a vertex that is not finite or not in front of the camera, or
    seen edge-on, is left out. Within a triangle depth is interpolated perspective-correctly
    and the normal from the vertices' area-weighted normals, so the surface is smooth across edges."""
    from lmgs_eval.data.raster import rasterize

    cx = w / 2 if cx is None else cx
    cy = h / 2 if cy is None else cy
    v = np.asarray(verts, np.float64)
    f = np.asarray(faces, np.int64)
    f = f[np.isfinite(v[f]).all((1, 2))]
    z = v[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([focal * v[:, 0] / z + cx, focal * v[:, 1] / z + cy], 1)
    uv[~np.isfinite(uv)] = 0.0  # vertices no kept triangle uses
    # vertex normals: area-weighted sums of the faces' normals, by the winding (turned below)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for c in range(3):
        np.add.at(vn, f[:, c], fn)
    attr = np.concatenate([np.ones((len(v), 2)), np.nan_to_num(vn)], 1)  # shade, alpha (unused here), normal
    _, at, zbuf, fid = rasterize(uv, np.nan_to_num(z), np.zeros((len(v), 2)), attr, f.astype(np.int32),
                                 np.zeros((1, 1, 3), np.float32), h, w, False)
    seen = fid >= 0
    depth = np.where(seen, zbuf, 0.0).astype(np.float32)
    n = at[..., 2:5].astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    k = fid[seen]
    if (fn[k] * v[f[k]].mean(1)).sum() > 0:  # the winding's normals face away from the camera where it sees the mesh
        n = -n
    normal = np.where(seen[..., None], n, 0.0).astype(np.float32)
    return depth, normal


def meet_mesh(centre: np.ndarray, axes: np.ndarray, w2c: np.ndarray, verts: np.ndarray, faces: np.ndarray, focal: float,
              w: int, h: int) -> tuple[np.ndarray, float]:
    """The ellipsoid's centre moved along the head's forward axis (the world's +z) so that its
    surface meets the mesh's outline: the median, over the frames given (``w2c [N, 4, 4]``,
    ``verts [N, V, 3]`` in each camera's coordinates), of the depth step from the mesh's edge to
    the ellipsoid just outside it. Returns ``(centre, step)``, the step in metres (positive: the
    ellipsoid lay behind the mesh). Without a frame that shows both, the centre is unchanged."""
    import cv2

    ring_k = np.ones((5, 5), np.uint8)
    steps = []
    for i in range(len(w2c)):
        if not np.isfinite(verts[i]).all():
            continue
        d_face, _ = render_mesh(verts[i], faces, focal, w, h)
        on = d_face > 0
        if not on.any():
            continue
        ring = (cv2.dilate(on.view(np.uint8), ring_k) > 0) & ~on
        edge = on & (cv2.dilate(ring.view(np.uint8), ring_k) > 0)
        d_ell, _ = render_prior(w2c[i], focal, w, h, centre, axes, ring)
        if (d_ell[ring] > 0).any():
            steps.append(float(np.median(d_ell[ring][d_ell[ring] > 0]) - np.median(d_face[edge])))
    if not steps:
        return centre, 0.0
    step = float(np.median(steps))
    return centre + np.array([0.0, 0.0, step]), step
