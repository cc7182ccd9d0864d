"""Person, head, neck and torso masks per frame; the background plate; the mouth mask.

The person comes from a learned segmenter (:mod:`lmgs_eval.data.ingest.segment`: MediaPipe's
selfie segmentation model): its probability map, at the frame's size, cut at one half, joined
with the face polygon of the landmarks and made one blob (:func:`person_from`). Half cover is
where the field's parsers draw the outline; hair, a cap and the shoulders down to the frame's
edge are person as the model sees them, with no colour model to confuse them with a background
of like colour.

The person is split by the landmarks: head = the person inside a generous head outline (an
ellipse over the brows, the jaw landmarks below) and, beside the jaw's upper part, all of the
person within the head's width (ears and hair move with the head); below the jaw line
lies neck, which does not move with the head. The neck is what lies below the chin within the
jaw's width, the torso the rest. The torso layer (:func:`torso_layer`) continues the neck and
torso up behind the head.

The plate (``bc.jpg``) assumes a static camera: each pixel is the median of the frames where
it is background (the person dilated away); pixels the person never uncovers are inpainted
(OpenCV Telea). The residual of the background against the plate is the static-camera check.
The soft rim of the outline (pixels under half cover that still carry the person's colour)
is background in the parsing but kept in the frame's images: ``gt_imgs`` take the person grown
against the plate (:func:`refine_person`), and ``torso_imgs`` the part of that rim that lies
nearer the neck and torso than the head (:func:`with_rim`), so those pixels do not take the
plate's colour.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PARSING_COLOURS = {"background": (255, 255, 255), "head": (255, 0, 0), "neck": (0, 255, 0), "torso": (0, 0, 255)}
HAIR_UP = 0.85  # head prior (the zoom check's): its top above the brows, in face heights (brow to chin)
HEAD_WIDE = 1.55  # head prior: half width in jaw half widths
LABEL_UP, LABEL_WIDE = 1.2, 2.2  # the head label's outline, as above: generous, since the person bounds it
CUT = 0.5  # the segmenter's probability at which a pixel is person
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
    (``jaw_out``: the jaw line pushed out by that fraction; 0: on the jaw landmarks themselves)."""
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


def face_polygon(lms: np.ndarray, shape) -> np.ndarray:
    """The face inside the jaw and the brows, bool ``shape``: always person."""
    return _poly(np.concatenate([lms[:17], lms[26:16:-1]]), shape)


def person_from(prob: np.ndarray, lms: np.ndarray) -> np.ndarray:
    """The person of one frame, bool ``[H, W]``: the segmenter's probability at or above
    :data:`CUT` with the face polygon, one blob (:func:`one_blob`)."""
    return one_blob((prob >= CUT) | face_polygon(lms, prob.shape))


def plate_difference(img: np.ndarray, plate: np.ndarray) -> np.ndarray:
    """Per pixel, the largest channel difference (grey levels) between the frame and the plate,
    uint8 ``[H, W]`` (exact: the difference of two uint8 values)."""
    import cv2

    d = cv2.absdiff(np.ascontiguousarray(img), np.ascontiguousarray(plate))
    if d.ndim == 2:
        return d
    c = cv2.split(d)
    out = c[0]
    for ch in c[1:]:
        out = cv2.max(out, ch)
    return out


def _median_u8(values: np.ndarray, where: np.ndarray) -> float:
    """``np.median(values[where])`` of a uint8 image, from its histogram (exact; the mean of the two
    middle values for an even count)."""
    import cv2

    hist = cv2.calcHist([values], [0], where.astype(np.uint8), [256], [0, 256]).ravel()
    cum = np.cumsum(hist.astype(np.int64))
    n = int(cum[-1])
    lo, hi = (int(np.searchsorted(cum, k, side="right")) for k in ((n - 1) // 2, n // 2))
    return 0.5 * (lo + hi)


def refine_person(person: np.ndarray, img: np.ndarray, plate: np.ndarray) -> np.ndarray:
    """The person grown, at full resolution, into the pixels next to it that differ from the plate.

    An outline drawn at half cover leaves out the soft rim of the person (hair and a collar's
    edge over a background of like colour most); in ``gt_imgs`` those pixels would take the
    plate's colour. Where the camera is still, what differs from the plate is the person: the
    mask grows one pixel at a time into pixels that differ by more than the noise (the floor or
    a multiple of the median difference away from the person, whichever is larger), at most
    :data:`GROW_REACH` of the frame side out. (Any channel order: the channels are treated alike.)
    """
    import cv2

    h, w = person.shape
    reach = max(1, int(round(GROW_REACH * max(h, w))))
    d = plate_difference(img, plate)
    m = person.astype(np.uint8)
    away = cv2.dilate(m, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)) == 0
    tau = max(DIFF_FLOOR, NOISE_K * _median_u8(d, away)) if away.any() else DIFF_FLOOR
    # a grown pixel is person or differs, so the mask may take what differs or was person at the start
    allowed = ((d > tau) | person).astype(np.uint8)
    step = np.ones((3, 3), np.uint8)
    count = cv2.countNonZero(m)
    for _ in range(reach):
        grown = cv2.bitwise_and(cv2.dilate(m, step), allowed)
        now = cv2.countNonZero(grown)  # the mask only grows: the same count is the same mask
        if now == count:
            break
        m, count = grown, now
    return m.astype(bool)


@dataclass(frozen=True)
class Parts:
    """One frame's parts, bool ``[H, W]`` each (disjoint)."""

    head: np.ndarray
    neck: np.ndarray
    torso: np.ndarray

    @classmethod
    def from_colour_map(cls, p: np.ndarray, bgr: bool = False) -> "Parts":
        """The parts of a parsing image (uint8 RGB ``[H, W, 3]`` in ER-NeRF's colours; ``bgr``: the
        channels in OpenCV's order)."""
        import cv2

        p = np.ascontiguousarray(p)

        def where(c):
            c = c[::-1] if bgr else c
            return cv2.inRange(p, c, c) > 0

        return cls(*(where(PARSING_COLOURS[k]) for k in ("head", "neck", "torso")))

    def colour_map(self, bgr: bool = False) -> np.ndarray:
        """The parsing image, uint8 RGB ``[H, W, 3]`` in ER-NeRF's colours (``bgr``: OpenCV's order);
        head over neck over torso where they overlap."""
        import cv2

        u8 = np.uint8
        label = np.maximum(np.maximum(self.torso.view(u8), self.neck.view(u8) * u8(2)), self.head.view(u8) * u8(3))
        lut = np.zeros((256, 1, 3), u8)
        for i, k in enumerate(("background", "torso", "neck", "head")):
            lut[i, 0] = PARSING_COLOURS[k][::-1] if bgr else PARSING_COLOURS[k]
        return cv2.LUT(cv2.merge([label, label, label]), lut)

    @property
    def person(self) -> np.ndarray:
        return self.head | self.neck | self.torso


def head_label(lms: np.ndarray, shape) -> np.ndarray:
    """Where the head label may lie, bool ``shape``: inside a generous head outline (:data:`LABEL_UP`,
    :data:`LABEL_WIDE`) on the jaw line itself, and beside the jaw's upper part, from the higher of
    its ends (landmarks 0 and 16) down to the lower of landmarks 2 and 14, within the outline's
    width: the ears, and hair that hangs there, move with the head."""
    h, w = shape
    zone = _poly(head_outline(lms, LABEL_UP, LABEL_WIDE, jaw_out=0.0), shape)
    jw = lms[16, 0] - lms[0, 0]
    jcx = 0.5 * (lms[0, 0] + lms[16, 0])
    yy, xx = np.ogrid[0:h, 0:w]
    yy, xx = yy + 0.5, xx + 0.5
    beside = (yy > min(lms[0, 1], lms[16, 1])) & (yy < max(lms[2, 1], lms[14, 1])) & (np.abs(xx - jcx) < 0.5 * LABEL_WIDE * jw)
    return zone | beside


def split_parts(person: np.ndarray, lms: np.ndarray) -> Parts:
    """Head = person inside :func:`head_label`; neck = the rest below the chin within the jaw's
    width, down to 0.7 face heights under the chin; torso = the remainder."""
    h, w = person.shape
    head = person & head_label(lms, (h, w))
    yy, xx = np.ogrid[0:h, 0:w]
    yy, xx = yy + 0.5, xx + 0.5
    fh = lms[8, 1] - lms[17:27, 1].mean()
    jw = lms[16, 0] - lms[0, 0]
    jcx = 0.5 * (lms[0, 0] + lms[16, 0])
    neck = person & ~head & (np.abs(xx - jcx) < 0.42 * jw) & (yy < lms[8, 1] + 0.7 * fh) & (yy > lms[4, 1])
    torso = person & ~head & ~neck
    return Parts(head, neck, torso)


def with_rim(parts: Parts, grown: np.ndarray) -> Parts:
    """``parts`` with the rim of ``grown`` (the person grown against the plate, :func:`refine_person`)
    added to the torso where it lies nearer the neck or torso than the head: the parts the torso
    layer is drawn from. The head's share of the rim is left to the head's renderer."""
    import cv2

    rim = grown & ~parts.head & ~parts.neck & ~parts.torso
    body = parts.neck | parts.torso
    if not rim.any() or not body.any():
        return parts
    to_head = cv2.distanceTransform((~parts.head).astype(np.uint8), cv2.DIST_L2, 3)
    to_body = cv2.distanceTransform((~body).astype(np.uint8), cv2.DIST_L2, 3)
    return Parts(parts.head, parts.neck, parts.torso | (rim & (to_body < to_head)))


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


def masked_median(stack: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Per pixel and channel, the median over the frames where ``keep`` holds, float32 ``[H, W, C]``
    of uint8 ``stack`` ``[K, H, W, C]`` and bool ``keep`` ``[K, H, W]`` (the mean of the two middle
    values for an even count; NaN's ``np.nanmedian`` with the others NaN gives the same numbers).
    Undefined where no frame is kept.

    One partial sort of the K values at two fixed ranks instead of a sort per pixel: of a pixel's
    ``K - k`` left-out values, ``(K - k) // 2`` are set below every value and the rest above, which
    puts its own median at ranks ``lo + (k - 1) // 2`` and ``lo + k // 2`` (``lo`` the number
    below): the same one or two ranks for every pixel whose ``k`` has the same parity."""
    K = len(stack)
    k = keep.sum(0, dtype=np.int32)
    lo = (K - k) // 2
    out = ~keep
    fill = np.where(np.cumsum(out, axis=0, dtype=np.int32) <= lo[None], np.int16(-1), np.int16(256))  # below / above 0-255
    x = np.where(out[..., None], fill[..., None], stack.astype(np.int16))
    flat = np.ascontiguousarray(x.reshape(K, -1).T)  # [H * W * C, K]
    c = stack.shape[-1]
    r1, r2 = (np.repeat(np.clip(lo + (k - j) // 2, 0, K - 1).ravel(), c) for j in (1, 0))
    ranks = np.unique(np.concatenate([r1, r2]))
    part = np.partition(flat, ranks, axis=1)
    a = np.take_along_axis(part, r1[:, None], 1)[:, 0].astype(np.float32)
    b = np.take_along_axis(part, r2[:, None], 1)[:, 0].astype(np.float32)
    return ((a + b) / np.float32(2)).reshape(stack.shape[1:])


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

        imgs = np.stack(self.stack)
        bg = ~np.stack(self.masks)
        seen = bg.any(0)
        med = np.where(seen[..., None], masked_median(imgs, bg), 0.0)
        imgs = imgs.astype(np.float32)
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
