"""The photograph as a deformable, textured 3D head, its cameras, and one rendered frame.

World units are metres; the head is fixed and the camera moves (like ER-NeRF): frame ``i``
has the camera-to-world ``c2w_i = H_i^{-1} c2w_0`` where ``H_i`` is the head motion and
``c2w_0`` looks at the face from ``(0, 0, D)`` along ``-z`` (OpenGL axes). The canonical
camera sees every vertex exactly where its texture coordinate lies in the photograph, so the
rest pose reproduces the photo.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from lmgs_eval.data import raster
from lmgs_eval.data.bundled import exact
from lmgs_eval.data.bundled.articulation import COLUMNS
from lmgs_eval.data.bundled.photo import TEX, Portrait, portrait

F_REL = 2.5  # focal length in frame widths (ER-NeRF's subjects: about 2.4-2.7)
JAW_WIDTH = 0.135  # metres between landmarks 0 and 16
JAW_MAX_DEG = 13.0
FEATHER = 9  # texture pixels of soft edge between the moving head and the static torso
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
ATLAS_ROWS = 64  # rows below the photo holding the procedural mouth textures


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _contour(mask: np.ndarray, n: int) -> np.ndarray:
    """``n`` points evenly spaced along the outer contour of a binary mask."""
    import cv2

    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    c = max(cs, key=cv2.contourArea)[:, 0, :].astype(np.float64) + 0.5
    seg = np.linalg.norm(np.diff(np.concatenate([c, c[:1]]), axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    t = np.linspace(0, s[-1], n, endpoint=False)
    cc = np.concatenate([c, c[:1]])
    return np.stack([np.interp(t, s, cc[:, 0]), np.interp(t, s, cc[:, 1])], 1)


def _atlas(tex: np.ndarray) -> np.ndarray:
    """The photo with procedural textures appended below: teeth, tongue, cavity."""
    rows = np.zeros((ATLAS_ROWS, TEX, 3), np.float32)
    x = np.arange(128) + 0.5
    # teeth: ivory with darker gaps every 16 px and a darker gum line at the top
    gap = 1.0 - 0.35 * exact.exp(-(((x % 16) - 8.0) / 1.3) ** 2 * 0.5)
    y = np.arange(ATLAS_ROWS)[:, None] + 0.5
    teeth = np.array([0.93, 0.89, 0.80], np.float32)[None, None] * gap[None, :, None] * (0.85 + 0.15 * (y / ATLAS_ROWS))[:, :, None]
    rows[:, 0:128] = teeth
    rows[:, 128:256] = np.array([0.72, 0.33, 0.34], np.float32)  # tongue
    rows[:, 256:384] = np.array([0.30, 0.07, 0.08], np.float32)  # cavity
    rows[:, 384:512] = np.array([0.75, 0.42, 0.42], np.float32)  # gums
    return np.concatenate([tex, rows], 0)


_PATCH = {"teeth": 0, "tongue": 128, "cavity": 256, "gums": 384}
# Triangles between the outer (48-59) and inner (60-67) lip contours of the 68-point scheme.
_LIP_RING = np.array([
    (48, 49, 60), (49, 61, 60), (49, 50, 61), (50, 62, 61), (50, 51, 62), (51, 52, 62), (52, 63, 62), (52, 53, 63),
    (53, 64, 63), (53, 54, 64), (54, 55, 64), (55, 65, 64), (55, 56, 65), (56, 66, 65), (56, 57, 66), (57, 58, 66),
    (58, 67, 66), (58, 59, 67), (59, 60, 67), (59, 48, 60),
])


@dataclass
class Frame:
    """One rendered frame at the output size."""

    rgb: np.ndarray  # [H, W, 3] float32 composited
    head_alpha: np.ndarray  # [H, W] float32
    mouth: np.ndarray  # [H, W] bool inside-mouth surfaces visible
    depth: np.ndarray  # [H, W] float32 camera z, 0 where no head surface
    normal: np.ndarray  # [H, W, 3] float32 camera-space unit normals (OpenCV), 0 elsewhere
    lms2d: np.ndarray  # [68, 2] pixels
    lms3d: np.ndarray  # [68, 3] world
    lip_gap: float  # inner-lip opening (landmarks 62-66) in metres


class HeadModel:
    """A photograph turned into a deformable head mesh with a mouth interior.

    Args:
        name: bundled subject name (``astronaut`` or ``hopper``).
        size: output frame size in pixels (square).
        hair: where the hair outside the head outline goes (:func:`photo.portrait`).
    """

    def __init__(self, name: str, size: int, hair: str = "layer") -> None:
        self.p: Portrait = portrait(name, hair)
        self.size = int(size)
        self.focal = F_REL * self.size
        self.atlas = _atlas(self.p.tex)
        self._build_mesh()

    # ------------------------------------------------------------------ construction
    def _build_mesh(self) -> None:
        import cv2
        import matplotlib.path as mpath
        from scipy.spatial import Delaunay

        p = self.p
        lms = p.lms
        head = (p.head > 0.5).astype(np.uint8)
        outer = _contour(cv2.dilate(head, np.ones((3, 3), np.uint8)), 96)
        inner_mask = cv2.erode(head, np.ones((2 * FEATHER + 1, 2 * FEATHER + 1), np.uint8))
        inner = _contour(inner_mask, 96)
        deep = cv2.erode(head, np.ones((2 * FEATHER + 17, 2 * FEATHER + 17), np.uint8)).astype(bool)
        step = 18
        gy, gx = np.mgrid[step // 2 : TEX : step, step // 2 : TEX : step]
        grid = np.stack([gx.ravel(), gy.ravel()], 1).astype(np.float64) + 0.5
        grid = grid[deep[gy.ravel(), gx.ravel()]]
        d = np.linalg.norm(grid[:, None] - lms[None], axis=2).min(1)
        grid = grid[d > 9.0]
        face_poly = np.concatenate([lms[:17], lms[26:16:-1]])
        # finer points inside the face for a smooth jaw deformation
        fgy, fgx = np.mgrid[step // 4 : TEX : step // 2, step // 4 : TEX : step // 2]
        fine = np.stack([fgx.ravel(), fgy.ravel()], 1).astype(np.float64) + 0.5
        in_face = mpath.Path(face_poly).contains_points(fine)
        fine = fine[in_face]
        fine = fine[np.linalg.norm(fine[:, None] - lms[None], axis=2).min(1) > 6.0]
        grid = grid[~mpath.Path(face_poly).contains_points(grid)]
        mc = lms[48:60].mean(0)
        lips_zone = mpath.Path(mc + 1.3 * (lms[48:60] - mc))
        fine = fine[~lips_zone.contains_points(fine)]
        grid = grid[~lips_zone.contains_points(grid)]
        pts = np.concatenate([lms, outer, inner, grid, fine])
        alpha = np.ones(len(pts))
        alpha[68 : 68 + len(outer)] = 0.0
        # Everything but the inner lips is triangulated (Delaunay); the lips are a fixed ring
        # of triangles between the outer (48-59) and inner (60-67) contours, so the hole
        # between the lips exists even where the photo shows a closed mouth.
        others = np.setdiff1d(np.arange(len(pts)), np.arange(60, 68))
        tri = others[Delaunay(pts[others]).simplices]
        cen = pts[tri].mean(1)
        keep = mpath.Path(outer).contains_points(cen)
        keep &= ~mpath.Path(lms[48:60]).contains_points(cen)
        edges = {tuple(sorted(e)) for t in tri[keep] for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
        missing = [(i, 48 + (i - 47) % 12) for i in range(48, 60) if tuple(sorted((i, 48 + (i - 47) % 12))) not in edges]
        if missing:
            raise RuntimeError(f"lip contour edges {missing} not in the triangulation")
        tri = np.concatenate([tri[keep], _LIP_RING])
        keep = np.ones(len(tri), bool)
        self.n_face_verts = len(pts)
        self.uv = pts.copy()
        self.alpha = alpha
        faces = tri[keep].astype(np.int32)

        # --- lift to 3D
        jw_tex = lms[16, 0] - lms[0, 0]
        self.k = JAW_WIDTH / jw_tex  # metres per texture pixel at the face
        z_face = 0.06
        self.D = self.k * F_REL * TEX + z_face
        ex = 0.5 * (lms[0, 0] + lms[16, 0])
        ey = lms[28, 1]
        a, b, c = 0.5 * JAW_WIDTH * 1.12, 0.5 * JAW_WIDTH * 1.55, 0.085
        x0 = (pts[:, 0] - ex) * self.k
        y0 = -(pts[:, 1] - ey) * self.k
        r2 = (x0 / a) ** 2 + (y0 / b) ** 2
        Z = c * np.sqrt(np.clip(1 - r2, 0.0, 1.0)) - 0.03
        self._ell = (ex, ey, a, b, c)
        bump = np.zeros(68)
        bump[27:31] = [0.006, 0.012, 0.02, 0.028]
        bump[31:36] = [0.008, 0.013, 0.017, 0.013, 0.008]
        bump[36:48] = -0.006
        bump[17:27] = 0.004
        bump[48:60] = 0.009
        bump[[48, 54]] = 0.002
        bump[60:68] = 0.007
        bump[6:11] = 0.004
        Z[:68] += bump
        # Perspective: the canonical camera must see each vertex at its texture position.
        depth = self.D - Z
        X = (pts[:, 0] - TEX / 2) * depth / (F_REL * TEX)
        Y = -(pts[:, 1] - TEX / 2) * depth / (F_REL * TEX)
        verts = np.stack([X, Y, Z], 1)

        # --- rest pose: inner lips closed (the photo may show a parted smile)
        for up, lo in ((61, 67), (62, 66), (63, 65)):
            m = 0.5 * (verts[up] + verts[lo])
            verts[up], verts[lo] = m, m.copy()
        self.face_faces = faces
        self._rest_face = verts

        # --- deformation weights (from rest positions)
        L = verts[:68]
        self.mouth_c = L[60:68].mean(0)
        hw = 0.5 * exact.norm3(L[54] - L[48])
        self.mouth_hw = hw
        fh = (lms[8, 1] - lms[17:27, 1].mean()) * self.k
        self.face_h = fh
        corner_y = 0.5 * (L[48, 1] + L[54, 1])
        wj = _smoothstep((corner_y - verts[:, 1] + 0.004) / (0.10 * fh))
        wj[[48, 54, 60, 64]] = 0.5
        wj[[49, 50, 51, 52, 53, 61, 62, 63]] = 0.0
        wj[[55, 56, 57, 58, 59, 65, 66, 67]] = 1.0
        self.w_jaw = wj
        self.jaw_pivot = np.array([L[27, 0], 0.5 * (L[0, 1] + L[16, 1]) + 0.01, -0.06])

        def g(centres, sigma):
            dd = np.linalg.norm(verts[:, None, :2] - centres[None, :, :2], axis=2).min(1)
            return exact.exp(-0.5 * (dd / sigma) ** 2)

        self.w_corner = g(L[[48, 54]], 0.35 * hw)
        self.w_lips = g(L[48:68], 0.18 * hw)
        self.w_lower = g(L[[56, 57, 58, 65, 66, 67]], 0.22 * hw) * (verts[:, 1] <= corner_y + 0.002)
        self.w_lower[[55, 56, 57, 58, 59, 65, 66, 67]] = 1.0
        self.w_lower[:48] = 0.0
        self.w_upper_inner = np.zeros(len(verts))
        self.w_upper_inner[[61, 62, 63]] = 1.0
        self.w_lower_inner = np.zeros(len(verts))
        self.w_lower_inner[[65, 66, 67]] = 1.0
        self.w_brow = g(L[17:27], 0.01) * (verts[:, 1] > L[36:48, 1].max())
        self.side = np.sign(verts[:, 0] - L[[48, 54], 0].mean())

        # --- mouth interior (attached to the head or to the jaw)
        self._build_interior()

    def _strip(self, xs, ys, zf, patch, u_span=(0, 128), jaw=0.0, shade=None):
        nx, ny = len(xs), len(ys)
        X, Yy = np.meshgrid(xs, ys)
        Z = zf(X, Yy)
        v = np.stack([X.ravel(), Yy.ravel(), Z.ravel()], 1)
        u0 = _PATCH[patch] + u_span[0]
        uu = u0 + (np.linspace(0, 1, nx)[None, :] * (u_span[1] - u_span[0])).repeat(ny, 0)
        vv = TEX + 2 + np.linspace(0, ATLAS_ROWS - 4, ny)[:, None].repeat(nx, 1)
        uv = np.stack([uu.ravel(), vv.ravel()], 1)
        f = []
        for j in range(ny - 1):
            for i in range(nx - 1):
                a = j * nx + i
                f += [[a, a + 1, a + nx], [a + 1, a + nx + 1, a + nx]]
        sh = np.ones(len(v)) if shade is None else shade(v)
        return v, uv, np.asarray(f), np.full(len(v), jaw), sh

    def surface(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """The smooth face surface (ellipsoid, no features) at world ``X, Y``: depth reference
        for the mouth interior, so teeth stay behind the lips and chin wherever they are."""
        ex, ey, a, b, c = self._ell
        x0 = X - (ex - TEX / 2) * self.k
        y0 = Y + (ey - TEX / 2) * self.k
        return c * np.sqrt(np.clip(1 - (x0 / a) ** 2 - (y0 / b) ** 2, 0.0, 1.0)) - 0.03

    def _build_interior(self) -> None:
        m = self.mouth_c
        hw = self.mouth_hw
        parts = []
        S = self.surface
        curve = lambda x: 0.006 * ((x - m[0]) / hw) ** 2  # noqa: E731 - the arch of the teeth
        side_dark = lambda v: 1.0 - 0.55 * np.clip(((v[:, 0] - m[0]) / (0.9 * hw)) ** 2, 0, 1)  # noqa: E731
        xs = m[0] + np.linspace(-0.85, 0.85, 13) * hw
        parts.append(self._strip(xs, m[1] + np.array([0.011, 0.003, -0.0035]), lambda X, Y: S(X, Y) - 0.002 - curve(X),
                                 "teeth", jaw=0.0, shade=side_dark))
        parts.append(self._strip(xs * 0.96 + m[0] * 0.04, m[1] + np.array([0.001, -0.004, -0.012]),
                                 lambda X, Y: S(X, Y) - 0.004 - curve(X), "teeth", jaw=1.0,
                                 shade=lambda v: 0.85 * side_dark(v)))
        tx = m[0] + np.linspace(-0.7, 0.7, 9) * hw
        tz = np.linspace(0.0, 1.0, 5)
        T, Sd = np.meshgrid(tx, tz)
        ty = m[1] - 0.007 + 0.004 * Sd + 0.003 * (1 - ((T - m[0]) / (0.7 * hw)) ** 2)
        tv = np.stack([T.ravel(), ty.ravel(), (S(T, ty) - 0.007 - 0.02 * Sd).ravel()], 1)
        t_uv = np.stack([(_PATCH["tongue"] + 4 + 120 * (T - tx[0]) / (tx[-1] - tx[0])).ravel(), (TEX + 2 + 56 * Sd).ravel()], 1)
        tf = []
        for j in range(len(tz) - 1):
            for i in range(len(tx) - 1):
                a = j * len(tx) + i
                tf += [[a, a + 1, a + len(tx)], [a + 1, a + len(tx) + 1, a + len(tx)]]
        parts.append((tv, t_uv, np.asarray(tf), np.ones(len(tv)), 0.85 - 0.45 * np.repeat(tz, len(tx))))
        cx = m[0] + np.linspace(-1.0, 1.0, 9) * hw
        cy = m[1] + np.linspace(0.012, -0.03, 7)
        cav = self._strip(cx, cy, lambda X, Y: S(X, Y) - 0.02, "cavity",
                          shade=lambda v: 1.0 - 0.5 * np.clip(((v[:, 0] - m[0]) / (1.0 * hw)) ** 2, 0, 1))
        cav_jaw = _smoothstep((m[1] - cav[0][:, 1]) / 0.01)
        parts.append((cav[0], cav[1], cav[2], cav_jaw, cav[4]))

        verts, uvs, faces, wj, shade, alpha = [self._rest_face], [self.uv], [self.face_faces], [self.w_jaw], [np.ones(len(self.uv))], [self.alpha]
        n = len(self._rest_face)
        self.face_count = len(self.face_faces)
        for v, uv, f, w, sh in parts:
            verts.append(v)
            uvs.append(uv)
            faces.append(f + n)
            wj.append(w)
            shade.append(sh)
            alpha.append(np.ones(len(v)))
            n += len(v)
        self.rest = np.concatenate(verts)
        self.uv_all = np.concatenate(uvs)
        self.faces = np.concatenate(faces).astype(np.int32)
        self.w_jaw_all = np.concatenate(wj)
        self.shade = np.concatenate(shade)
        self.alpha_all = np.concatenate(alpha)
        nf = len(self.rest) - len(self._rest_face)
        pad = lambda w: np.concatenate([w, np.zeros(nf)])  # noqa: E731
        self.w_corner, self.w_lips, self.w_lower, self.w_brow, self.side = map(pad, (self.w_corner, self.w_lips, self.w_lower, self.w_brow, self.side))
        self.w_upper_inner, self.w_lower_inner = pad(self.w_upper_inner), pad(self.w_lower_inner)

    # ------------------------------------------------------------------ deformation
    def deform(self, a: np.ndarray) -> np.ndarray:
        """Vertex positions ``[V, 3]`` (world) for one articulation row (``COLUMNS``)."""
        c = dict(zip(COLUMNS, map(float, a)))
        v = self.rest.copy()
        hw = self.mouth_hw
        # lips: spread / narrow and round (protrude); the rounded mouth also opens a little
        v[:, 0] += self.side * self.w_corner * hw * (0.12 * c["lip_width"] - 0.22 * c["lip_round"])
        v[:, 2] += self.w_lips * 0.007 * c["lip_round"]
        v[:, 1] += (self.w_upper_inner - self.w_lower_inner) * 0.0015 * c["lip_round"]
        # f/v: the lower lip rises and tucks behind the upper teeth; p/b/m keep the lips shut
        lower_free = 1.0 - self.w_lips * np.clip(max(c["lip_closure"], c["lip_teeth"]), 0, 1)
        v[:, 1] += -self.w_lower_inner * 0.0016 * c["lip_teeth"]
        v[:, 2] += -self.w_lower * 0.006 * c["lip_teeth"]
        # jaw rotation about a horizontal axis near the ears
        th = np.deg2rad(JAW_MAX_DEG) * np.clip(c["jaw"], -0.1, 1.2)
        wj = self.w_jaw_all * np.where(self.w_jaw_all > 0, lower_free, 1.0)
        rel = v - self.jaw_pivot
        ang = th * wj
        cs, sn = exact.cos(ang), exact.sin(ang)
        y = rel[:, 1] * cs - rel[:, 2] * sn
        z = rel[:, 1] * sn + rel[:, 2] * cs
        # the lips and interior follow fully; teeth and tongue keep their shape (rigid jaw)
        v[:, 1] = y + self.jaw_pivot[1]
        v[:, 2] = z + self.jaw_pivot[2]
        # blink: upper lids meet the lower lids
        bl = np.clip(c["blink"], 0, 1)
        for up, lo in ((37, 41), (38, 40), (43, 47), (44, 46)):
            tgt = v[lo] + 0.15 * (v[up] - v[lo])
            v[up] = v[up] + bl * (tgt - v[up])
        v[:, 1] += self.w_brow * 0.004 * c["brow"]
        return v

    # ------------------------------------------------------------------ cameras
    def c2w0(self) -> np.ndarray:
        m = np.eye(4)
        m[2, 3] = self.D
        return m

    def head_pose(self, a: np.ndarray) -> np.ndarray:
        """The head's rigid motion ``H`` ``[4, 4]`` (rotation about the neck pivot, then translation)."""
        c = dict(zip(COLUMNS, map(float, a)))
        yaw, pitch, roll = np.deg2rad([c["yaw"], c["pitch"], c["roll"]])
        cy, sy, cp, sp, cr, sr = (f(float(x)) for x in (yaw, pitch, roll) for f in (math.cos, math.sin))
        Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
        Rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
        R = exact.matmul(exact.matmul(Ry, Rx), Rz)
        piv = self.neck_pivot()
        H = np.eye(4)
        H[:3, :3] = R
        H[:3, 3] = piv - exact.matvec3(R, piv) + np.array([c["tx"], c["ty"], c["tz"]])
        return H

    def neck_pivot(self) -> np.ndarray:
        L = self._rest_face[:68]
        return np.array([L[27, 0], L[8, 1] - 0.01, -0.05])

    def c2w(self, a: np.ndarray) -> np.ndarray:
        """Camera-to-world (OpenGL) of a frame: the head motion turned into camera motion."""
        return exact.matmul(exact.inv4(self.head_pose(a)), self.c2w0())

    # ------------------------------------------------------------------ rendering
    @functools.cached_property
    def _under(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        import cv2

        s = self.size
        rs = lambda im: cv2.resize(im, (s, s), interpolation=cv2.INTER_AREA)  # noqa: E731
        ta, bc, torso = rs(self.p.under_torso), rs(self.p.background), rs(self.p.under)
        # The head is composited over exactly the plate the files carry (torso_imgs over bc.jpg;
        # generator 2). Generator 1 used the photo itself, whose hair and hat around the head's
        # outline no plate-based method could know (the "GT head on plate" row showed it).
        plate = torso * ta[..., None] + bc * (1 - ta[..., None])
        return plate.astype(np.float32), ta, bc, torso

    def static_layers(self, zoom: float = 1.0) -> dict[str, np.ndarray]:
        """Frame-size static images: ``torso`` (torso over background) and its ``torso_alpha``,
        ``bc``, ``neck`` mask. The head is composited over ``torso`` by ``torso_alpha`` over ``bc``.

        ``zoom``: the focal length relative to :attr:`focal`; the layers as that camera sees them
        (:meth:`zoomed`)."""
        import cv2

        _, ta, bc, torso = self._under
        neck = cv2.resize(self.p.neck.astype(np.float32), (self.size, self.size), interpolation=cv2.INTER_AREA)
        if zoom != 1.0:
            ta, bc, torso, neck = (self.zoomed(x, zoom) for x in (ta, bc, torso, neck))
        return {"torso": torso, "torso_alpha": ta, "bc": bc, "neck": neck > 0.5}

    def zoomed(self, img: np.ndarray, zoom: float) -> np.ndarray:
        """A frame-size image as a camera with ``zoom`` times the focal length sees it: scaled by
        ``zoom`` about the principal point (the frame centre); uncovered borders are mirrored."""
        import cv2

        c = self.size / 2 - 0.5  # the frame centre in OpenCV's pixel-centre coordinates
        m = np.array([[zoom, 0.0, (1 - zoom) * c], [0.0, zoom, (1 - zoom) * c]])
        return cv2.warpAffine(img, m, (self.size, self.size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)

    def render(self, a: np.ndarray, ss: int = 2, geometry: bool = True, focal: float | None = None) -> Frame:
        """Render one frame for articulation row ``a``; ``focal`` (pixels) other than
        :attr:`focal` renders a zoomed camera: the head projected with it, over the plate
        scaled by the same ratio."""
        v = self.deform(a)
        w2c = exact.inv4(exact.matmul(self.c2w(a), _GL_TO_CV))
        pc = exact.matmul(v, w2c[:3, :3].T) + w2c[:3, 3]
        s = self.size
        f = self.focal if focal is None else float(focal)
        xy = np.stack([f * pc[:, 0] / pc[:, 2] + s / 2, f * pc[:, 1] / pc[:, 2] + s / 2], 1)
        attr = np.stack([self.shade, self.alpha_all], 1)
        if ss > 1:
            rgb, at, _, _ = raster.rasterize(xy * ss, pc[:, 2], self.uv_all, attr, self.faces, self.atlas, s * ss, s * ss, True)
            a_hi = at[:, :, 1]
            prem = raster.downsample(rgb * a_hi[:, :, None], ss)
            alpha = raster.downsample(a_hi, ss)
        else:
            rgb, at, _, _ = raster.rasterize(xy, pc[:, 2], self.uv_all, attr, self.faces, self.atlas, s, s, True)
            alpha = at[:, :, 1]
            prem = rgb * alpha[:, :, None]
        under = self._under[0] if f == self.focal else self.zoomed(self._under[0], f / self.focal)
        out = prem + (1.0 - alpha[:, :, None]) * under
        lip_gap = exact.norm3(v[62] - v[66])
        if not geometry:
            return Frame(out.astype(np.float32), alpha.astype(np.float32), None, None, None, xy[:68].copy(), v[:68].copy(), lip_gap)
        n = self._normals(v)
        ncam = exact.matmul(n, w2c[:3, :3].T)
        flip = np.sum(ncam * pc, axis=1) > 0  # make normals face the camera
        ncam[flip] *= -1
        attr1 = np.concatenate([attr, ncam], 1)
        _, at1, zb, fid = raster.rasterize(xy, pc[:, 2], self.uv_all, attr1, self.faces, self.atlas, s, s, False)
        solid = at1[:, :, 1] >= 0.5
        depth = np.where(solid, zb, 0.0).astype(np.float32)
        nrm = at1[:, :, 2:5]
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=2, keepdims=True), 1e-8)
        nrm = np.where(solid[:, :, None], nrm, 0.0).astype(np.float32)
        mouth = solid & (fid >= self.face_count)
        return Frame(out.astype(np.float32), alpha.astype(np.float32), mouth, depth, nrm, xy[:68].copy(), v[:68].copy(), lip_gap)

    def _normals(self, v: np.ndarray) -> np.ndarray:
        f = self.faces
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        # orient every face towards +z (the camera side) before accumulating
        fn *= np.where(fn[:, 2:3] < 0, -1.0, 1.0)
        n = np.zeros_like(v)
        for k in range(3):
            np.add.at(n, f[:, k], fn)
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
