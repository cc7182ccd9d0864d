"""The two public-domain face photographs, their 68 landmarks, crop and segmentation.

Everything here works in *texture space*: the square crop around the face resampled to
``TEX`` x ``TEX`` pixels, continuous coordinates (pixel ``i`` covers ``[i, i + 1)``, so dlib's
integer pixel indices are shifted by +0.5).
"""

from __future__ import annotations

import functools
import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lmgs_eval.data.bundled import exact
from lmgs_eval.errors import UserError

TEX = 512


@dataclass(frozen=True)
class PhotoSpec:
    """How to frame one photograph.

    Attributes:
        source: where the photo comes from (for ``meta.json``).
        package: the installed package that ships it.
        jaw_frac: jaw width (landmark 0 to 16) as a fraction of the crop width.
        centre_dy: crop centre below the nose tip, as a fraction of the crop size.
        hair_up: top of the head region above the brows, in face heights (brow to chin).
        head_wide: half width of the head region, in jaw half widths.
    """

    source: str
    package: str
    jaw_frac: float
    centre_dy: float
    hair_up: float
    head_wide: float


PHOTOS = {
    "astronaut": PhotoSpec("skimage.data.astronaut() (astronaut.png, NASA photograph of Eileen Collins, public domain)",
                           "scikit-image", 0.35, 0.02, 0.8, 1.75),
    "hopper": PhotoSpec("matplotlib sample_data/grace_hopper.jpg (US Navy photograph of Grace Hopper, public domain)",
                        "matplotlib", 0.42, -0.07, 0.85, 1.45),
}


def load_photo(name: str) -> np.ndarray:
    """The full photograph as uint8 RGB ``[H, W, 3]``."""
    if name == "astronaut":
        import skimage.data

        return np.ascontiguousarray(skimage.data.astronaut()[:, :, :3])
    if name == "hopper":
        import cv2
        import matplotlib.cbook

        path = matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise UserError(f"{path}: matplotlib's sample photo is missing or unreadable")
        return np.ascontiguousarray(img[:, :, ::-1])
    raise UserError(f"bundled subject {name!r}: unknown (known: {', '.join(PHOTOS)})")


@functools.lru_cache(maxsize=1)
def _dlib_models():
    import dlib

    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or not spec.submodule_search_locations:
        raise UserError("face-recognition-models is not installed (it holds dlib's 68-landmark model); run `make`")
    path = Path(list(spec.submodule_search_locations)[0]) / "models" / "shape_predictor_68_face_landmarks.dat"
    if not path.exists():
        raise UserError(f"{path}: dlib's 68-landmark model is missing")
    return dlib.get_frontal_face_detector(), dlib.shape_predictor(str(path))


def detect_landmarks(img: np.ndarray, upsample: int = 1) -> np.ndarray | None:
    """dlib's 68 landmarks ``[68, 2]`` (continuous pixel coordinates) of the largest face, or None."""
    import dlib

    det, sp = _dlib_models()
    img = np.ascontiguousarray(img)
    faces = det(img, upsample)
    if len(faces) == 0:
        return None
    box = max(faces, key=lambda r: r.width() * r.height())
    shape = sp(img, box)
    return np.array([[p.x + 0.5, p.y + 0.5] for p in shape.parts()], np.float64)


def landmarks_in_box(img: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    """dlib's 68 landmarks given a face box ``(left, top, right, bottom)`` (no detection)."""
    import dlib

    _, sp = _dlib_models()
    r = dlib.rectangle(*[int(round(v)) for v in box])
    shape = sp(np.ascontiguousarray(img), r)
    return np.array([[p.x + 0.5, p.y + 0.5] for p in shape.parts()], np.float64)


@dataclass(frozen=True)
class Portrait:
    """A photograph prepared for rendering, all in texture space (``TEX`` x ``TEX``).

    Attributes:
        tex: float32 ``[TEX, TEX, 3]`` the square crop around the face.
        lms: ``[68, 2]`` landmarks.
        head: float32 ``[TEX, TEX]`` head (face + hair) mask in [0, 1].
        person: bool ``[TEX, TEX]`` the whole person (head, neck, torso).
        neck: bool ``[TEX, TEX]`` neck part of the person (below the head).
        under: float32 ``[TEX, TEX, 3]`` what lies behind the head: torso and neck (the neck
            continued upwards under the chin) over the background.
        under_torso: float32 ``[TEX, TEX]`` alpha of the torso layer (neck + shoulders).
        background: float32 ``[TEX, TEX, 3]`` the photo with the person painted out.

    The renderer composites the head over ``under`` (torso, by ``under_torso``) over
    ``background``: exactly the plate the subject files carry (``torso_imgs`` over ``bc.jpg``).
    """

    name: str
    spec: PhotoSpec
    tex: np.ndarray
    lms: np.ndarray
    head: np.ndarray
    person: np.ndarray
    neck: np.ndarray
    under: np.ndarray
    under_torso: np.ndarray
    background: np.ndarray
    crop: tuple[float, float, float]  # x0, y0, size of the crop in photo pixels


def _crop(img: np.ndarray, x0: float, y0: float, size: float) -> np.ndarray:
    import cv2

    s = TEX / size
    # continuous coordinates: dst = (src - x0) * s; in pixel indices i_d = s * i_s + (0.5 s - 0.5 - s x0)
    m = np.array([[s, 0, 0.5 * s - 0.5 - s * x0], [0, s, 0.5 * s - 0.5 - s * y0]], np.float64)
    return cv2.warpAffine(img, m, (TEX, TEX), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


# OpenCV hands a bicubic resize of 8-bit images to Intel IPP, whose kernels are chosen by the
# CPU (AVX2: l9, AVX-512: k0) and round a few values differently. OpenCV's own fixed-point bicubic
# (IPP off) gives the same bytes on every CPU (checked with its AVX2, AVX and FMA3 code paths
# disabled). The subjects of generator 2 were made with IPP's AVX2 kernel, which differs from
# OpenCV's own at these values of the two bundled backgrounds; they are put back, so every CPU
# builds those bytes. Keyed by the sha256 of OpenCV's own result: any other image is left as is.
_IPP_AVX2_CUBIC = {
    "0af2e81378d4d05996ee423327230b477d96968ef3d75f8343b9ab4ceba92438":  # astronaut
        ((118, 407, 0, 203), (264, 245, 0, 214), (425, 384, 2, 230), (493, 501, 1, 210), (494, 506, 0, 209)),
    "e7d78aa0b4559b5a1f2a6f29abf0c8e1530dd2bf224ccf7f268cca5069fbe1b8": ((282, 403, 1, 141),),  # hopper
}


def _upsample_cubic(img: np.ndarray) -> np.ndarray:
    """``img`` (uint8) resized bicubically to ``TEX`` x ``TEX``, the same bytes on every CPU."""
    import hashlib

    import cv2

    was = cv2.ipp.useIPP()
    cv2.ipp.setUseIPP(False)
    try:
        out = cv2.resize(img, (TEX, TEX), interpolation=cv2.INTER_CUBIC)
    finally:
        cv2.ipp.setUseIPP(was)
    for y, x, c, v in _IPP_AVX2_CUBIC.get(hashlib.sha256(out.tobytes()).hexdigest(), ()):
        out[y, x, c] = v
    return out


def _poly_mask(pts: np.ndarray, shape=(TEX, TEX)) -> np.ndarray:
    import cv2

    m = np.zeros(shape, np.uint8)
    cv2.fillPoly(m, [np.round(pts * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    return m.astype(bool)


def head_outline(lms: np.ndarray, spec: PhotoSpec, n: int = 72, jaw_out: float = 0.04) -> np.ndarray:
    """A prior outline of the head (face + hair) ``[n, 2]``: the jaw below, an ellipse above.

    ``jaw_out``: the jaw line is pushed out from the jaw's centre by this fraction and down by
    half of it in face heights (the photographs' soft jaw edge; 0: the jaw landmarks themselves).
    """
    jaw = lms[:17]
    brow_y = lms[17:27, 1].mean()
    chin_y = lms[8, 1]
    fh = chin_y - brow_y
    cx = 0.5 * (jaw[0, 0] + jaw[16, 0])
    half = 0.5 * (jaw[16, 0] - jaw[0, 0]) * spec.head_wide
    top = brow_y - spec.hair_up * fh
    ear_y = 0.5 * (jaw[0, 1] + jaw[16, 1])
    # upper part: half ellipse from the right ear over the top to the left ear
    ang = np.linspace(0.0, np.pi, n // 2)
    upper = np.stack([cx + half * exact.cos(ang), ear_y - (ear_y - top) * exact.sin(ang)], 1)
    # lower part: from the left ear down along the jaw (a little outside it) to the right ear
    c = jaw.mean(0)
    lower = c + (jaw - c) * (1.0 + jaw_out) + np.array([0.0, 0.5 * jaw_out * fh])
    lower = np.concatenate([[[cx - half, ear_y + 0.1 * fh]], lower, [[cx + half, ear_y + 0.1 * fh]]])
    return np.concatenate([upper, lower])  # closed polygon: over the top, then back along the jaw


HAIR = ("layer", "head")  # where the hair outside the head outline goes (:func:`portrait`)


def check_hair(hair: str) -> None:
    if hair not in HAIR:
        raise UserError(f"hair {hair!r}: one of {', '.join(HAIR)}")


@functools.lru_cache(maxsize=4)
def portrait(name: str, hair: str = "layer") -> Portrait:
    """Load, crop and segment the photograph of bundled subject ``name`` (cached).

    ``hair``: ``"layer"`` (the subjects as built so far) keeps the head to the person inside
    the head outline (:func:`head_outline`); hair beyond it (a rim above the crown, locks
    beside the jaw) stays in the static torso layer, so the video shows it still while the
    head moves, and the subject's own parsing labels it torso. ``"head"`` makes all the hair
    above the jaw's lower half part of the head, as on a camera, where hair moves with the head.
    """
    check_hair(hair)
    import cv2

    spec = PHOTOS.get(name)
    if spec is None:
        raise UserError(f"bundled subject {name!r}: unknown (known: {', '.join(PHOTOS)})")
    img = load_photo(name)
    lm = detect_landmarks(img)
    if lm is None:
        raise UserError(f"{spec.source}: dlib found no face in the photograph")
    jaw_w = lm[16, 0] - lm[0, 0]
    size = jaw_w / spec.jaw_frac
    cx = 0.5 * (lm[0, 0] + lm[16, 0])
    cy = lm[30, 1] + spec.centre_dy * size
    x0, y0 = cx - size / 2, cy - size / 2
    tex = _crop(img, x0, y0, size).astype(np.float32) / 255.0
    lms = (lm - [x0, y0]) * (TEX / size)

    # --- person segmentation: GrabCut seeded by face geometry (seeded RNG: deterministic)
    fh = lms[8, 1] - lms[17:27, 1].mean()
    outline = head_outline(lms, spec)
    head_prior = _poly_mask(outline)
    face = _poly_mask(np.concatenate([lms[:17], lms[26:16:-1]]))
    gc = np.full((TEX, TEX), cv2.GC_PR_BGD, np.uint8)
    gc[head_prior] = cv2.GC_PR_FGD
    body_top = int(lms[8, 1] + 0.35 * fh)
    jcx = 0.5 * (lms[0, 0] + lms[16, 0])
    jw = lms[16, 0] - lms[0, 0]
    yy, xx = np.mgrid[0:TEX, 0:TEX] + 0.5
    shoulders = (yy > lms[8, 1] + 0.1 * fh) & (np.abs(xx - jcx) < 0.45 * jw + 1.6 * np.maximum(0, yy - lms[8, 1]))
    gc[shoulders] = cv2.GC_PR_FGD
    gc[(yy > body_top) & (np.abs(xx - jcx) < 0.35 * jw)] = cv2.GC_FGD
    gc[cv2.erode(face.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)] = cv2.GC_FGD
    gc[:, : int(0.04 * TEX)][yy[:, : int(0.04 * TEX)] < lms[8, 1]] = cv2.GC_BGD
    gc[:, -int(0.04 * TEX):][yy[:, -int(0.04 * TEX):] < lms[8, 1]] = cv2.GC_BGD
    outside_head = ~_poly_mask(head_outline(lms, PhotoSpec("", "", spec.jaw_frac, 0, spec.hair_up + 0.25, spec.head_wide * 1.25)))
    gc[outside_head & (yy < lms[0, 1])] = cv2.GC_BGD
    cv2.setRNGSeed(0)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    u8 = np.ascontiguousarray((tex * 255).round().astype(np.uint8)[:, :, ::-1])
    cv2.grabCut(u8, gc, None, bgd, fgd, 6, cv2.GC_INIT_WITH_MASK)
    person = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    person = cv2.morphologyEx(person.astype(np.uint8), cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    person = cv2.morphologyEx(person, cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8))
    n, lab, stats, _ = cv2.connectedComponentsWithStats(person, 8)
    if n > 1:
        keep = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        person = (lab == keep).astype(np.uint8)
    person = person.astype(bool) | face

    # --- head = person inside the head prior; the rest of the person is neck and torso
    if hair == "head":  # every person pixel above the collar the GrabCut seeds allow the head
        jaw = lms[:17]
        ear_y = 0.5 * (jaw[0, 1] + jaw[16, 1])
        beside = (yy > ear_y) & (yy < max(lms[3, 1], lms[13, 1])) & (np.abs(xx - jcx) < 0.5 * jw * spec.head_wide * 1.25)
        head_prior = head_prior | ~outside_head | beside
    head = person & head_prior
    head = cv2.morphologyEx(head.astype(np.uint8), cv2.MORPH_OPEN, np.ones((7, 7), np.uint8)).astype(bool) | face
    neck = person & ~head & (np.abs(xx - jcx) < 0.42 * jw) & (yy < lms[8, 1] + 0.7 * fh) & (yy > lms[4, 1])

    # --- background with the person painted out
    hole = cv2.dilate(person.astype(np.uint8), np.ones((7, 7), np.uint8))
    small = cv2.resize(u8, (TEX // 4, TEX // 4), interpolation=cv2.INTER_AREA)
    hole_s = cv2.resize(hole, (TEX // 4, TEX // 4), interpolation=cv2.INTER_NEAREST)
    bg_s = cv2.inpaint(small, hole_s, 5, cv2.INPAINT_TELEA)
    bg = _upsample_cubic(bg_s)
    bg = np.where(hole[:, :, None].astype(bool), bg, u8)[:, :, ::-1].astype(np.float32) / 255.0

    # --- under the head: torso as in the photo, the neck continued upwards behind the chin
    torso = person & ~head
    under = np.where(torso[:, :, None], tex, bg)
    alpha = torso.astype(np.float32)
    jaw_y = np.interp(xx[0], lms[:17, 0], lms[:17, 1])[None, :]
    ext = head & (yy > jaw_y - 0.3 * fh) & (yy > lms[33, 1]) & (np.abs(xx - jcx) < 0.4 * jw)
    colsrc = torso & (np.abs(xx - jcx) < 0.4 * jw)
    for x in np.nonzero(ext.any(0))[0]:
        ys = np.nonzero(colsrc[:, x] & (yy[:, x] > lms[8, 1]))[0]
        if len(ys) == 0:
            continue
        y_top = ys[0]
        src = tex[min(y_top + 3, TEX - 1), x]
        rows = np.nonzero(ext[:, x])[0]
        under[rows, x] = src * 0.85  # in the shadow of the chin
        alpha[rows, x] = 1.0
    blur = cv2.GaussianBlur(under, (0, 0), 1.0)
    under = np.where(alpha[:, :, None] > 0, blur, under)
    return Portrait(name, spec, tex, lms, head.astype(np.float32), person, neck, under.astype(np.float32),
                    alpha, bg, (float(x0), float(y0), float(size)))
