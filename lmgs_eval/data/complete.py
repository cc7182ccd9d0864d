"""Completing a plain processed folder: 3D landmarks and a head prior from what it already has.

An ER-NeRF / TalkingGaussian folder carries 2D landmarks, cameras and a focal length, but no
3D landmarks and no depth or normal maps, which lmgs and the 3DGS methods need to place their
first Gaussians. The same fit ``ingest`` uses derives them:

* **3D landmarks**: each 2D landmark on its camera ray, at the depth of the head's centre (the
  world origin, where the field's trackers put the head) plus the generic face relief
  (:func:`lmgs.landmarks.lift_2d_landmarks`, relief x :data:`geometry.RELIEF`, as the ingest's template);
* **head prior**: the ellipsoid of :mod:`geometry`, placed on the per-point median of those 3D
  landmarks; depth and normal maps are ray-cast from it on demand (no files), inside each
  frame's head parsing mask.

The result is cached outside the user's folder, under ``<cache>/derived/<key>``, where ``key``
is the sha256 of the files it is derived from (both transforms files and every ``.lms``), so an
edited folder is derived afresh and the user's folder is never written to. The subject's notes
say what was derived and where it is, and every record made from it carries those notes.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DERIVED_VERSION = "2"  # 2: depth / normal priors cover the whole head mask (the sheet beyond the ellipsoid)

# What a processed folder of the field holds (ER-NeRF's process.py, plus TalkingGaussian's
# teeth masks): ``ori_imgs`` carries the frames and their ``.lms``. No 3D landmarks, no depth
# or normal maps, no manifest.
PLAIN_LAYOUT = ("ori_imgs", "gt_imgs", "torso_imgs", "parsing", "teeth_mask", "bc.jpg", "aud.wav", "au.csv",
                "track_params.pt", "transforms_train.json", "transforms_val.json")


@dataclass(frozen=True)
class HeadPrior:
    """A head ellipsoid in the subject's world (its centre and semi-axes, world units)."""

    centre: tuple[float, float, float]
    axes: tuple[float, float, float]
    source: str  # how it was obtained, for notes and records

    def render(self, w2c: np.ndarray, focal: float, cx: float, cy: float, w: int, h: int, mask: np.ndarray):
        """Depth ``[H, W]`` and normals ``[H, W, 3]`` (OpenCV camera) inside ``mask``."""
        from lmgs_eval.data.geometry import render_prior

        return render_prior(w2c, focal, w, h, np.asarray(self.centre), np.asarray(self.axes), mask, cx=cx, cy=cy)


def content_key(root: Path, n: int) -> str:
    """sha256 of the files the derivation reads: the transforms files and every ``.lms``."""
    h = hashlib.sha256(DERIVED_VERSION.encode())
    for name in ("transforms_train.json", "transforms_val.json", "transforms.json"):
        p = root / name
        if p.exists():
            h.update(name.encode() + p.read_bytes())
    for i in range(n):
        h.update((root / "ori_imgs" / f"{i}.lms").read_bytes())
    return h.hexdigest()


def derive(root: Path, lms2d: np.ndarray, c2w: np.ndarray, focal: float, cx: float, cy: float,
           cache_dir: Path | None = None) -> tuple[np.ndarray, HeadPrior, Path]:
    """3D landmarks ``[N, 68, 3]`` and the head prior of a folder, from the cache or computed.

    ``cache_dir``: where the derived results are kept (default ``<cache>/derived``)."""
    from lmgs.landmarks import MEAN_FACE_DEPTH, lift_2d_landmarks
    from lmgs.fileio import atomic_write
    from lmgs_eval.data.geometry import RELIEF, head_ellipsoid
    from lmgs_eval.paths import cache_root

    root = Path(root)
    key = content_key(root, len(lms2d))
    cache = (Path(cache_dir) if cache_dir is not None else cache_root() / "derived") / key[:24]
    meta_p, lms_p = cache / "derived.json", cache / "lms3d.npy"
    if meta_p.exists() and lms_p.exists():
        meta = json.loads(meta_p.read_text())
        lms3d = np.load(lms_p)
        if lms3d.shape == (len(lms2d), 68, 3) and meta.get("key") == key:
            return lms3d, HeadPrior(tuple(meta["centre"]), tuple(meta["axes"]), meta["source"]), cache
    width_px = np.linalg.norm(lms2d[:, 0] - lms2d[:, 16], axis=1)
    # the relief of lift_2d_landmarks is in face widths; scaled as the ingest template's
    w2c = np.linalg.inv(c2w.astype(np.float64) @ np.diag([1.0, -1.0, -1.0, 1.0]))
    D = w2c[:, 2, 3]
    prior = MEAN_FACE_DEPTH[None] * RELIEF * (width_px * D / focal)[:, None]
    lms3d = lift_2d_landmarks(lms2d, c2w, focal, cx, cy, depth_prior=prior).numpy().astype(np.float32)
    template = np.median(lms3d, axis=0)
    centre, axes = head_ellipsoid(template.astype(np.float64))
    source = (f"derived by lmgs_eval.data.complete v{DERIVED_VERSION} from the folder's 2D landmarks and cameras "
              f"(sha256 {key[:16]}...)")
    cache.mkdir(parents=True, exist_ok=True)
    import io as _io

    buf = _io.BytesIO()
    np.save(buf, lms3d)
    atomic_write(lms_p, buf.getvalue())
    atomic_write(meta_p, json.dumps({"key": key, "folder": str(root), "centre": centre.tolist(), "axes": axes.tolist(),
                                     "source": source, "version": DERIVED_VERSION}, indent=1))
    return lms3d, HeadPrior(tuple(centre.tolist()), tuple(axes.tolist()), source), cache


def strip_to_plain(src: Path, dst: Path) -> Path:
    """Copy a complete subject folder to ``dst`` with only the entries of :data:`PLAIN_LAYOUT`.

    What a user with a folder made by the field's preprocessing has; :func:`derive` completes
    it when it is read. ``dst`` must not exist. ``ori_imgs`` keeps its ``.jpg`` and ``.lms``.
    """
    import shutil

    src, dst = Path(src), Path(dst)
    missing = [n for n in PLAIN_LAYOUT if not (src / n).exists()]
    if missing:
        raise FileNotFoundError(f"{src}: no {', '.join(missing)} to copy")
    dst.mkdir(parents=True)
    for n in PLAIN_LAYOUT:
        if (src / n).is_dir():
            keep = (".jpg", ".lms") if n == "ori_imgs" else None
            shutil.copytree(src / n, dst / n, ignore=None if keep is None else
                            (lambda d, names, keep=keep: [x for x in names if not x.endswith(keep)]))
        else:
            shutil.copy2(src / n, dst / n)
    return dst
