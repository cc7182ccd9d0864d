"""An ingested subject against the ground truth of the same footage (a bundled subject).

The bundled generator writes each subject's raw video (``<name>.mp4``) beside the truth it
was rendered from; ingesting that video and comparing gives the figures of ``design.md``:

* ``landmark_px``: mean distance of the 68 landmarks, per frame then over frames (pixels);
  ``inner_landmark_px``: the same without the jaw contour (0-16), whose detected points are
  silhouette points while the generator's are surface points (they part under yaw);
* ``rotation_deg``: head rotation error after removing one constant rotation (the two world
  frames differ by a fixed rotation: the template's axes are not the generator's), mean over
  frames, and ``rotation_spread_deg``: the truth's own mean rotation away from its mean pose
  (what a fit that returned a constant pose would score);
* ``translation_rel``: camera-to-head distance error relative to the true distance (scale of
  the world removed: the ingest's world unit is the template's jaw width);
* for a truth whose focal length changes (``focal_per_frame.npy``: a zooming camera):
  ``focal_range_true``, the truth's focal range relative to its mean, and
  ``distance_zoom_slope``, the slope of the per-frame distance error on the relative focal
  change (-1: a fit with one focal length put the whole zoom into the camera's distance);
* ``head_iou`` and ``person_iou``: intersection over union of the head parsing masks and of the
  whole person's, mean over frames; ``gt_psnr``: the ``gt_imgs`` against the truth's (the true
  frames), mean PSNR over frames: what the masks and the plate lose (and the codec, for a lossy
  video);
* ``depth_rel``, ``normal_deg``, ``geometry_cover``: the depth / normal priors against the
  truth's maps (:func:`geometry_error`);
* ``plate_psnr``: PSNR of ``bc.jpg`` over the pixels that are background in every frame of
  the truth (where the background is visible); ``audio_identical``: ``aud.wav`` sample-equal.

For a method trained on both folders, :func:`edge_band` (with
:func:`lmgs_eval.metrics.image.psnr_outside`) gives the PSNR away from the head's outline: the
outline decides which pixels the test frame's own torso layer supplies and which the method must
render, and two parsings of the same footage draw it differently (see ``design.md``, "End to end").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _rotations(c2w: np.ndarray) -> np.ndarray:
    return np.linalg.inv(c2w @ GL_TO_CV)[:, :3, :3]  # world-to-camera rotation, OpenCV camera


def rotation_error_deg(c2w_true: np.ndarray, c2w_est: np.ndarray) -> tuple[float, float]:
    """Mean head-rotation error (degrees) up to one constant rotation, and the truth's spread."""
    from scipy.spatial.transform import Rotation

    rt, re = Rotation.from_matrix(_rotations(c2w_true)), Rotation.from_matrix(_rotations(c2w_est))
    d = rt.inv() * re  # R_true^T R_est = Q (constant) if the estimate is right
    q = d.mean()
    err = np.degrees((d * q.inv()).magnitude())
    spread = np.degrees((rt * rt.mean().inv()).magnitude())
    return float(err.mean()), float(spread.mean())


def distance_track(c2w_true: np.ndarray, c2w_est: np.ndarray) -> np.ndarray:
    """Signed relative error ``[N]`` of the per-frame camera distance to the world origin after
    one best scale."""
    dt = np.linalg.norm(c2w_true[:, :3, 3], axis=1)
    de = np.linalg.norm(c2w_est[:, :3, 3], axis=1)
    s = float(np.dot(dt, de) / np.dot(de, de))
    return (s * de - dt) / dt


def distance_error_rel(c2w_true: np.ndarray, c2w_est: np.ndarray) -> float:
    """Relative error of the per-frame camera distance to the world origin after one best scale."""
    return float(np.mean(np.abs(distance_track(c2w_true, c2w_est))))


def zoom_error(c2w_true: np.ndarray, c2w_est: np.ndarray, focals: np.ndarray) -> dict[str, float]:
    """Where a zoom went in a fit with one focal length: the truth's focal range (relative to its
    mean) and the slope of the per-frame distance error on the relative focal change."""
    x = focals / focals.mean() - 1.0
    y = distance_track(c2w_true, c2w_est)
    return {"focal_range_true": float(np.ptp(x)),
            "distance_zoom_slope": float((x - x.mean()) @ (y - y.mean()) / ((x - x.mean()) @ (x - x.mean())))}


def masks_and_frames(true_dir: Path, est_dir: Path, n: int) -> dict[str, float]:
    """``head_iou`` and ``person_iou`` (intersection over union of the parsing's head, and of all
    it does not call background), mean over frames; ``gt_psnr``: PSNR (dB) of the ``gt_imgs``
    against the truth's, mean over frames."""
    from lmgs_eval.data.images import read_rgb, read_rgb_u8

    def iou(a, b):
        u = (a | b).sum()
        return (a & b).sum() / u if u else 1.0

    head, person, gt = [], [], []
    for i in range(n):
        pa, pb = (read_rgb_u8(d / "parsing" / f"{i}.png") for d in (true_dir, est_dir))
        head.append(iou(*(np.all(p == (255, 0, 0), axis=-1) for p in (pa, pb))))
        person.append(iou(*(~np.all(p == 255, axis=-1) for p in (pa, pb))))
        ga, gb = (read_rgb(d / "gt_imgs" / f"{i}.jpg") for d in (true_dir, est_dir))
        gt.append(-10 * np.log10(max(float(np.mean((ga - gb) ** 2)), 1e-12)))
    return {"head_iou": float(np.mean(head)), "person_iou": float(np.mean(person)), "gt_psnr": float(np.mean(gt))}


def head_masks(folder: Path, ids) -> np.ndarray:
    """The head of each frame's parsing map (ER-NeRF's red), bool ``[len(ids), H, W]``."""
    from lmgs_eval.data.images import read_rgb_u8

    return np.stack([np.all(read_rgb_u8(Path(folder) / "parsing" / f"{int(i)}.png") == (255, 0, 0), axis=-1) for i in ids])


def edge_band(masks: np.ndarray, radius: int) -> np.ndarray:
    """Pixels within ``radius`` pixels (chessboard distance) of each mask's outline, bool like ``masks``:
    the mask dilated minus the mask eroded by a ``2 radius + 1`` square."""
    import cv2

    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    out = np.zeros(masks.shape, bool)
    for t, m in enumerate(np.asarray(masks, np.uint8)):
        out[t] = (cv2.dilate(m, k) > 0) & ~(cv2.erode(m, k, borderType=cv2.BORDER_REPLICATE) > 0)
    return out


def plate_psnr(true_dir: Path, est_dir: Path, n: int) -> tuple[float, float]:
    """PSNR (dB) of the plate where the truth's background is visible in every frame, and the
    share of the frame that is."""
    from lmgs_eval.data.images import read_rgb, read_rgb_u8

    vis = None
    for i in range(n):
        bg = np.all(read_rgb_u8(true_dir / "parsing" / f"{i}.png") == 255, axis=-1)
        vis = bg if vis is None else vis & bg
    a, b = read_rgb(true_dir / "bc.jpg"), read_rgb(est_dir / "bc.jpg")
    mse = float(np.mean((a[vis] - b[vis]) ** 2)) if vis.any() else float("nan")
    return float(-10 * np.log10(max(mse, 1e-12))), float(vis.mean())


def geometry_error(t, e) -> dict[str, float]:
    """Depth and normal priors against the truth's maps, over pixels where both have a surface:
    median relative depth error after the one world scale (camera distances) is removed, mean
    normal angle (degrees), and the share of the truth's surface the prior covers."""
    if not (t.has_geometry and e.has_geometry):
        return {}
    dt = np.linalg.norm(t.c2w[:, :3, 3], axis=1)
    de = np.linalg.norm(e.c2w[:, :3, 3], axis=1)
    scale = float(np.dot(dt, de) / np.dot(de, de))
    rel, ang, cover = [], [], []
    for i in np.linspace(0, t.n_frames - 1, min(10, t.n_frames)).round().astype(int):
        a, b = t.depth(i), e.depth(i) * scale
        both = (a > 0) & (b > 0)
        cover.append(both.sum() / max(1, (a > 0).sum()))
        rel.append(np.abs(b[both] - a[both]) / a[both])
        na, nb = t.normal(i)[both], e.normal(i)[both]
        ang.append(np.degrees(np.arccos(np.clip((na * nb).sum(1), -1, 1))))
    return {"depth_rel": float(np.median(np.concatenate(rel))), "normal_deg": float(np.mean(np.concatenate(ang))),
            "geometry_cover": float(np.mean(cover))}


def _snr(ref: np.ndarray, est: np.ndarray) -> float:
    n = min(len(ref), len(est))
    noise = float(np.sum((ref[:n] - est[:n]) ** 2))
    return float("inf") if noise == 0 else float(10 * np.log10(np.sum(ref[:n] ** 2) / noise))


def compare(true_dir: str | Path, est_dir: str | Path) -> dict[str, float]:
    """Every figure of the module docstring for an ingest of a bundled subject's own video."""
    from lmgs_eval.data.layout import read_subject

    t, e = read_subject(Path(true_dir)), read_subject(Path(est_dir))
    if (t.n_frames, t.width) != (e.n_frames, e.width):
        raise ValueError(f"{est_dir}: {e.n_frames} frames of {e.width} px, the truth has {t.n_frames} of {t.width}")
    n = t.n_frames
    rot, spread = rotation_error_deg(t.c2w, e.c2w)
    psnr, vis = plate_psnr(t.root, e.root, n)
    return {
        "landmark_px": float(np.linalg.norm(t.landmarks - e.landmarks, axis=2).mean()),
        "inner_landmark_px": float(np.linalg.norm(t.landmarks[:, 17:] - e.landmarks[:, 17:], axis=2).mean()),
        "mouth_landmark_px": float(np.linalg.norm(t.landmarks[:, 48:] - e.landmarks[:, 48:], axis=2).mean()),
        "rotation_deg": rot,
        "rotation_spread_deg": spread,
        "translation_rel": distance_error_rel(t.c2w, e.c2w),
        "focal_rel": float(e.focal / t.focal),
        **masks_and_frames(t.root, e.root, n),
        "plate_psnr": psnr,
        "plate_visible": vis,
        "blink_corr": float(np.corrcoef(t.blink, e.blink)[0, 1]) if t.blink.std() > 0 and e.blink.std() > 0 else float("nan"),
        "audio_identical": bool(len(t.audio) == len(e.audio) and np.array_equal(t.audio, e.audio)),
        "audio_snr_db": _snr(t.audio, e.audio),
        **geometry_error(t, e),
        **(zoom_error(t.c2w, e.c2w, np.load(t.root / "focal_per_frame.npy")) if (t.root / "focal_per_frame.npy").is_file() else {}),
    }


def lossless_video(truth_root: Path, out: Path) -> Path:
    """A bundled subject's frames (``ori_imgs``, every RGB value kept) and ``aud.wav`` as a lossless
    mp4 (x264's RGB encoder at quantiser 0): an ingest of it starts from exactly the truth's frames."""
    from lmgs_eval.data.audio import read_wav
    from lmgs_eval.data.images import read_rgb_u8
    from lmgs_eval.data.video import write_video

    n = len(list((truth_root / "ori_imgs").glob("*.jpg")))
    frames = np.stack([read_rgb_u8(truth_root / "ori_imgs" / f"{i}.jpg") for i in range(n)])
    audio, sr = read_wav(truth_root / "aud.wav")
    write_video(out, frames, 25, audio[:, 0], sr, lossless=True)  # the generator writes mono
    return out


def bundled_truth(spec, hair: str, tmp: Path, data_root=None, motion: str | None = None) -> Path:
    """The bundled subject ``spec`` (a ``BundledSpec``): ``hair="layer"`` without ``motion`` as the
    registry builds it (cached under the data root); otherwise a copy built under ``tmp`` (not a
    registry subject: it goes with ``tmp``), with ``hair="head"`` its hair all moving with the head,
    with ``motion`` (``"turn"``, ``"zoom"``) the generator's motion variant."""
    from lmgs_eval.data.registry import ensure_bundled

    if hair == "layer" and motion is None:
        return ensure_bundled(spec, data_root, progress=False)
    from lmgs_eval.data.bundled import build

    root = Path(tmp) / "truth" / f"{spec.folder}-{hair}-{motion or 'still'}"
    root.mkdir(parents=True)
    build(spec.name, root, size=spec.size, seconds=spec.seconds, seed=spec.seed, progress=False, hair=hair, motion=motion)
    return root
