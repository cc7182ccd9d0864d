"""Person, head, neck and torso masks per frame; the background plate; the mouth mask.

No learned parser is available offline (ER-NeRF uses BiSeNet), so the person is separated
from the background by GrabCut on a reduced copy of each frame, seeded by the face geometry
the landmarks give (the same seeding the bundled generator uses on its photographs):
certainly person inside the face and below the chin, probably person in a head prior (an
ellipse over the brows, the jaw below) and the shoulders, certainly background in the upper
frame corners outside a widened head prior. The person is then split by the head prior:
head (face and hair) inside it, down to the jaw line itself (what lies below it is neck, which
does not move with the head), the neck below the chin within the jaw's width, the torso the
rest. The torso layer (:func:`torso_layer`) continues the neck and torso up behind the head.

GrabCut learns its colour models on every ``KEYFRAME``-th frame and only cuts, with the models
frozen, in between. The core of the head prior is seeded as certain person, so the hair's
colours belong to the person's model; hair that hangs outside the prior (long hair beside the
neck) is found only where its colour differs from the background's.

The plate (``bc.jpg``) assumes a static camera: each pixel is the median of the frames where
it is background (the person dilated away); pixels the person never uncovers are inpainted
(OpenCV Telea). The residual of the background against the plate is the static-camera check.
With the plate known, each frame's person is grown at full resolution into the pixels next to
it that differ from the plate (:func:`refine_person`): GrabCut's reduced copy misses the soft
rim of the outline, whose pixels would otherwise take the plate's colour in ``gt_imgs``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PARSING_COLOURS = {"background": (255, 255, 255), "head": (255, 0, 0), "neck": (0, 255, 0), "torso": (0, 0, 255)}
GRABCUT_SIDE = 160  # GrabCut runs at this size (the masks are upsampled with a smooth edge)
KEYFRAME = 25  # frames between GrabCut's colour-model updates (frozen models in between)
HAIR_UP = 0.85  # head prior: its top above the brows, in face heights (brow to chin)
HEAD_WIDE = 1.55  # head prior: half width in jaw half widths
PLATE_MARGIN = 0.012  # the person grown by this fraction of the frame before its pixels count as background
GROW_REACH = 0.025  # against the plate, the person grows by at most this fraction of the frame side...
DIFF_FLOOR, NOISE_K = 10.0, 5.0  # ...into pixels that differ from it by over max(DIFF_FLOOR, NOISE_K x the background's median difference)


def _poly(pts: np.ndarray, shape) -> np.ndarray:
    import cv2

    m = np.zeros(shape, np.uint8)
    cv2.fillPoly(m, [np.round(np.asarray(pts) * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    return m.astype(bool)


def head_outline(lms: np.ndarray, hair_up: float = HAIR_UP, head_wide: float = HEAD_WIDE, n: int = 72,
                 jaw_out: float = 0.04) -> np.ndarray:
    """A prior outline of the head (face + hair) ``[n, 2]``: the jaw below, an ellipse above
    (``jaw_out``: the jaw line pushed out by that fraction, as GrabCut's prior; 0 for the label)."""
    from lmgs_eval.data.bundled.photo import PhotoSpec
    from lmgs_eval.data.bundled.photo import head_outline as outline

    return outline(lms, PhotoSpec("", "", 0.0, 0.0, hair_up, head_wide), n, jaw_out)


def one_blob(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected region of ``mask`` with its holes filled. A hole is background
    that does not reach the frame's edge: background cut off from one corner by a head that
    touches the top edge is still background."""
    import cv2

    m = mask.astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, 8)
    if n > 1:
        m = (lab == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
    out = np.pad(m, 1)  # a ring of background joins every stretch of background on the edge
    cv2.floodFill(out, None, (0, 0), 2)
    return (out[1:-1, 1:-1] != 2)


def person_mask(img: np.ndarray, lms: np.ndarray, model: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, tuple]:
    """The person (head, neck, torso) in one frame, bool ``[H, W]``, by seeded GrabCut.

    With ``model`` (the colour models a keyframe learned) one graph cut runs with the models
    frozen (``GC_EVAL_FREEZE_MODEL``: a fifth of the cost); without, three iterations learn
    them from the seeds. Returns the mask and the models.
    """
    import cv2

    h, w = img.shape[:2]
    s = min(1.0, GRABCUT_SIDE / max(h, w))
    sh, sw = max(8, int(round(h * s))), max(8, int(round(w * s)))
    small = cv2.resize(img, (sw, sh), interpolation=cv2.INTER_AREA)
    l = lms * [sw / w, sh / h]
    yy, xx = np.mgrid[0:sh, 0:sw] + 0.5
    fh = l[8, 1] - l[17:27, 1].mean()
    jw = l[16, 0] - l[0, 0]
    jcx = 0.5 * (l[0, 0] + l[16, 0])
    gc = np.full((sh, sw), cv2.GC_PR_BGD, np.uint8)
    prior = head_outline(l)
    gc[_poly(prior, (sh, sw))] = cv2.GC_PR_FGD
    # the head prior's core (shrunk to 80 % about the face centre) is certainly face or hair:
    # seeding it makes the hair's colours part of the person's model, not the background's
    fc = l[:68].mean(0)
    gc[_poly(fc + 0.8 * (prior - fc), (sh, sw))] = cv2.GC_FGD
    shoulders = (yy > l[8, 1] + 0.1 * fh) & (np.abs(xx - jcx) < 0.45 * jw + 1.6 * np.maximum(0, yy - l[8, 1]))
    gc[shoulders] = cv2.GC_PR_FGD
    gc[(yy > l[8, 1] + 0.35 * fh) & (np.abs(xx - jcx) < 0.3 * jw)] = cv2.GC_FGD
    face = _poly(np.concatenate([l[:17], l[26:16:-1]]), (sh, sw))
    gc[cv2.erode(face.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)] = cv2.GC_FGD
    outside = ~_poly(head_outline(l, HAIR_UP + 0.3, HEAD_WIDE * 1.3), (sh, sw))
    gc[outside & (yy < l[0, 1])] = cv2.GC_BGD
    cv2.setRNGSeed(0)
    bgr = np.ascontiguousarray(small[:, :, ::-1])
    seeds = gc.copy()
    try:
        if model is not None:
            bgd, fgd = model[0].copy(), model[1].copy()
            cv2.grabCut(bgr, gc, None, bgd, fgd, 1, cv2.GC_EVAL_FREEZE_MODEL)
        else:
            bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
            cv2.grabCut(bgr, gc, None, bgd, fgd, 3, cv2.GC_INIT_WITH_MASK)
            model = (bgd, fgd)
    except cv2.error:  # a degenerate frame (e.g. uniform): keep the seeds
        gc = seeds
    fg = ((gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)).astype(np.uint8)
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    fg = one_blob(fg.astype(bool)).astype(np.float32)
    big = cv2.resize(cv2.GaussianBlur(fg, (0, 0), 0.7), (w, h), interpolation=cv2.INTER_LINEAR)
    return (big >= 0.5) | _poly(np.concatenate([lms[:17], lms[26:16:-1]]), (h, w)), model


def plate_difference(img: np.ndarray, plate: np.ndarray) -> np.ndarray:
    """Per pixel, the largest channel difference (grey levels) between the frame and the plate,
    float32 ``[H, W]``."""
    return np.abs(img.astype(np.float32) - plate.astype(np.float32)).max(-1)


def refine_person(person: np.ndarray, img: np.ndarray, plate: np.ndarray) -> np.ndarray:
    """The person of :func:`person_mask` grown, at full resolution, into the pixels next to it
    that differ from the plate.

    GrabCut cuts a reduced copy of the frame, so its outline can miss a pixel or two of the
    person all round, and more where hair or a collar meets a background of like colour; those
    pixels would take the plate's colour in ``gt_imgs``. Where the camera is still, what differs
    from the plate is the person: the mask grows one pixel at a time into pixels that differ by
    more than the noise (the floor or a multiple of the median difference away from the person,
    whichever is larger), at most :data:`GROW_REACH` of the frame side out.
    """
    import cv2

    h, w = person.shape
    reach = max(1, int(round(GROW_REACH * max(h, w))))
    d = plate_difference(img, plate)
    away = ~cv2.dilate(person.astype(np.uint8), np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)).astype(bool)
    tau = max(DIFF_FLOOR, NOISE_K * float(np.median(d[away]))) if away.any() else DIFF_FLOOR
    differs = (d > tau).astype(np.uint8)
    m = person.astype(np.uint8)
    step = np.ones((3, 3), np.uint8)
    for _ in range(reach):
        grown = cv2.dilate(m, step) & (differs | m)
        if np.array_equal(grown, m):
            break
        m = grown
    return m.astype(bool)


@dataclass(frozen=True)
class Parts:
    """One frame's parts, bool ``[H, W]`` each (disjoint)."""

    head: np.ndarray
    neck: np.ndarray
    torso: np.ndarray

    @classmethod
    def from_colour_map(cls, p: np.ndarray) -> "Parts":
        """The parts of a parsing image (uint8 RGB ``[H, W, 3]`` in ER-NeRF's colours)."""
        return cls(*(np.all(p == PARSING_COLOURS[k], axis=-1) for k in ("head", "neck", "torso")))

    def colour_map(self) -> np.ndarray:
        """The parsing image, uint8 RGB ``[H, W, 3]`` in ER-NeRF's colours."""
        out = np.full(self.head.shape + (3,), 255, np.uint8)
        out[self.torso] = PARSING_COLOURS["torso"]
        out[self.neck] = PARSING_COLOURS["neck"]
        out[self.head] = PARSING_COLOURS["head"]
        return out

    @property
    def person(self) -> np.ndarray:
        return self.head | self.neck | self.torso


def split_parts(person: np.ndarray, lms: np.ndarray) -> Parts:
    """Head = person inside the head prior; neck = the rest below the chin within the jaw's
    width, down to 0.7 face heights under the chin; torso = the remainder."""
    h, w = person.shape
    head = person & _poly(head_outline(lms, jaw_out=0.0), (h, w))
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    fh = lms[8, 1] - lms[17:27, 1].mean()
    jw = lms[16, 0] - lms[0, 0]
    jcx = 0.5 * (lms[0, 0] + lms[16, 0])
    neck = person & ~head & (np.abs(xx - jcx) < 0.42 * jw) & (yy < lms[8, 1] + 0.7 * fh) & (yy > lms[4, 1])
    torso = person & ~head & ~neck
    return Parts(head, neck, torso)


# The torso layer continued up behind the head, as the field's processing writes ``torso_imgs``:
# lengths in pixels of a 512-pixel frame (scaled with the frame), per-pixel darkening upwards.
NECK_UP, TORSO_UP, NECK_PUSH = 48, 8, 4
UP_DARKEN = 0.98


def _continue_up(rgb: np.ndarray, alpha: np.ndarray, part: np.ndarray, head: np.ndarray, length: int, push: int,
                 darken: float) -> None:
    """Continue ``part`` straight up behind ``head`` in place: in each column whose topmost
    ``part`` pixel lies under a head pixel, the colour ``push`` pixels below that top (at most
    the column's last part pixel) is repeated upwards for ``length`` pixels, darkened by
    ``darken`` per pixel (in shadow under the chin)."""
    h = part.shape[0]
    cols = np.nonzero(part.any(0))[0]
    if cols.size == 0:
        return
    top = part[:, cols].argmax(0)
    keep = (top > 0) & head[np.maximum(top - 1, 0), cols]
    cols, top = cols[keep], top[keep]
    if cols.size == 0:
        return
    bottom = h - 1 - part[::-1, cols].argmax(0)
    src = np.minimum(top + push, bottom)
    colour = rgb[src, cols].astype(np.float32)
    k = np.arange(length)
    ys = src[None, :] - k[:, None]  # [length, m]
    ok = ys >= 0
    xs = np.broadcast_to(cols[None, :], ys.shape)
    shade = (darken ** k)[:, None, None] * colour[None]
    rgb[ys[ok], xs[ok]] = np.clip(np.rint(shade[ok]), 0, 255).astype(rgb.dtype)
    alpha[ys[ok], xs[ok]] = True


def torso_layer(img: np.ndarray, parts: "Parts") -> tuple[np.ndarray, np.ndarray]:
    """``torso_imgs`` of one frame: RGB uint8 ``[H, W, 3]`` and its alpha, bool ``[H, W]``.

    The frame on the neck and torso, and behind the head what lies there: the neck (grown 3
    pixels up and down) and the torso continued straight up into the head's region, darkened
    as they go and lightly blurred, as ER-NeRF's processing writes its torso images. Methods
    composite the head over this layer over ``bc.jpg``, so at the chin's soft edge the head
    blends into neck, not into the plate's background.
    """
    import cv2

    h, w = parts.head.shape
    s = max(h, w) / 512.0
    fill = img.copy()
    up = np.zeros((h, w), bool)
    _continue_up(fill, up, parts.torso, parts.head, max(1, round(TORSO_UP * s)) + 1, 0, UP_DARKEN ** (1 / s))
    grow = max(1, round(3 * s))
    neck = cv2.dilate(parts.neck.astype(np.uint8), np.ones((2 * grow + 1, 1), np.uint8)).astype(bool)
    _continue_up(fill, up, neck, parts.head, max(1, round((NECK_UP + NECK_PUSH) * s)) + 1, max(1, round(NECK_PUSH * s)),
                 UP_DARKEN ** (1 / s))
    alpha = parts.neck | parts.torso
    up &= ~alpha  # the frame's own neck and torso pixels stay as filmed
    rgb = img.copy()
    rgb[up] = cv2.GaussianBlur(fill, (0, 0), max(0.5, s))[up]
    return rgb, alpha | up


def mouth_mask(lms: np.ndarray, shape) -> np.ndarray:
    """The inside of the mouth: the polygon of the inner lips (landmarks 60-67)."""
    return _poly(lms[60:68], shape)


class PlateBuilder:
    """Accumulates background pixels over frames; :meth:`plate` gives ``bc.jpg``."""

    def __init__(self, h: int, w: int, max_frames: int, n_frames: int) -> None:
        self.keep = set(np.linspace(0, n_frames - 1, min(max_frames, n_frames)).round().astype(int).tolist())
        self.stack: list[np.ndarray] = []
        self.ids: list[int] = []
        self.masks: list[np.ndarray] = []
        self.shape = (h, w)

    def add(self, k: int, img: np.ndarray, person: np.ndarray) -> None:
        import cv2

        if k not in self.keep:
            return
        grow = max(3, int(round(PLATE_MARGIN * max(self.shape))) * 2 + 1)
        self.stack.append(img)
        self.ids.append(int(k))
        self.masks.append(cv2.dilate(person.astype(np.uint8), np.ones((grow, grow), np.uint8)).astype(bool))

    def plate(self) -> tuple[np.ndarray, np.ndarray, list[float]]:
        """The plate uint8 ``[H, W, 3]``, where it was seen (bool ``[H, W]``), and the per-frame
        median absolute difference (grey levels) of the background against it."""
        import cv2

        imgs = np.stack(self.stack).astype(np.float32)
        bg = ~np.stack(self.masks)
        seen = bg.any(0)
        data = np.where(bg[..., None], imgs, np.nan)
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                med = np.nanmedian(data, axis=0)
        med = np.where(seen[..., None], med, 0.0)
        plate = np.clip(np.rint(med), 0, 255).astype(np.uint8)
        if not seen.all():
            h, w = self.shape
            q = 4 if min(h, w) >= 128 else 1
            small = cv2.resize(plate, (w // q, h // q), interpolation=cv2.INTER_AREA)
            hole = cv2.resize((~seen).astype(np.uint8), (w // q, h // q), interpolation=cv2.INTER_NEAREST)
            hole = cv2.dilate(hole, np.ones((3, 3), np.uint8))
            filled = cv2.inpaint(np.ascontiguousarray(small[:, :, ::-1]), hole, 5, cv2.INPAINT_TELEA)[:, :, ::-1]
            big = cv2.resize(filled, (w, h), interpolation=cv2.INTER_CUBIC)
            plate = np.where(seen[..., None], plate, big)
        resid = []
        for img, b in zip(imgs, bg):
            d = np.abs(img - plate.astype(np.float32)).mean(-1)[b]
            resid.append(float(np.median(d)) if d.size else 0.0)
        return plate, seen, resid
