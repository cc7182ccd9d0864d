"""Reader of the ER-NeRF / TalkingGaussian processed-subject layout.

The layout (the repository's ``docs/field.md``), ``data/<ID>/``::

    <ID>.mp4  aud.wav  bc.jpg  track_params.pt  au.csv
    ori_imgs/<i>.jpg  ori_imgs/<i>.lms  gt_imgs/<i>.jpg  torso_imgs/<i>.png  parsing/<i>.png
    teeth_mask/<i>.npy (optional)  aud_ds.npy / aud_hu.npy / aud_eo.npy / aud.npy (optional)
    transforms_train.json  transforms_val.json

plus, for the project's bundled subjects only: ``lms3d.npy``, ``depth/``, ``normal/``,
``meta.json``. One reader serves real and bundled subjects.

Every problem is either a :class:`~lmgs_eval.errors.UserError` naming the file and what
is wrong, or a documented repair recorded in ``Subject.notes``:

* audio at another sample rate or in stereo: resampled to 16 kHz / mixed to mono;
* audio shorter than the frames by less than one frame: padded with silence;
* audio features longer than the frame count: the extra rows are ignored;
* a split in the transforms files that is not the field's first-10/11: kept as given.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from lmgs.errors import InputError
from lmgs_eval.data.audio import SAMPLE_RATE, load_audio
from lmgs_eval.data.complete import derive as derive_priors
from lmgs_eval.data.images import image_size
from lmgs_eval.data.subject import FPS, Subject
from lmgs_eval.errors import UserError

SAMPLES_PER_FRAME = SAMPLE_RATE // FPS  # 640


MIN_SPLIT_FRAMES = 2  # the fewest frames the first-10/11 split leaves a training and a test frame


def split_point(n_frames: int) -> int:
    """Index of the first test frame: the field's ``int(n * 10 / 11)``."""
    return int(n_frames * 10 / 11)


def _read_json(path: Path) -> dict:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None


def _read_transforms(root: Path) -> tuple[dict, list[dict], list[dict]]:
    files = [root / "transforms_train.json", root / "transforms_val.json"]
    missing = [f.name for f in files if not f.exists()]
    if missing:
        if (root / "transforms.json").exists() and len(missing) == 2:
            files = [root / "transforms.json"]
        else:
            raise UserError(f"{root}: missing {', '.join(missing)} (expected ER-NeRF's processed layout)")
    parts = []
    top: dict = {}
    for f in files:
        d = _read_json(f)
        for key in ("focal_len", "frames"):
            if key not in d:
                raise UserError(f"{f}: no '{key}' entry")
        if not isinstance(d["frames"], list):
            raise UserError(f"{f}: 'frames' must be a list")
        for k, fr in enumerate(d["frames"]):
            if "img_id" not in fr or "transform_matrix" not in fr:
                raise UserError(f"{f}: frame {k} lacks 'img_id' or 'transform_matrix'")
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
            if m.shape != (4, 4) or not np.all(np.isfinite(m)):
                raise UserError(f"{f}: frame {k} (img_id {fr['img_id']}): transform_matrix must be a finite 4x4, got shape {m.shape}")
        top = top or d
        parts.append(d["frames"])
    train = parts[0]
    val = parts[1] if len(parts) > 1 else []
    return top, train, val


def _read_lms(path: Path) -> np.ndarray:
    if not path.exists():
        raise UserError(f"{path}: landmark file not found")
    try:
        a = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise UserError(f"{path}: not a text file of 'x y' rows ({exc})") from None
    if a.shape != (68, 2):
        raise UserError(f"{path}: expected 68 rows of 'x y', got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise UserError(f"{path}: landmarks contain non-finite values")
    return a


def read_au_csv(path: Path, n_frames: int) -> dict[str, np.ndarray]:
    """Read OpenFace's ``au.csv``: every ``AUxx_r`` column, keyed without the leading space."""
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    if not rows:
        raise UserError(f"{path}: empty file")
    header = [h.strip() for h in rows[0]]
    cols = [i for i, h in enumerate(header) if h.startswith("AU") and h.endswith("_r")]
    if "AU45_r" not in header:
        raise UserError(f"{path}: no ' AU45_r' column (OpenFace action-unit intensities expected)")
    body = rows[1:]
    if len(body) < n_frames:
        raise UserError(f"{path}: {len(body)} rows for {n_frames} frames")
    try:
        vals = np.asarray([[float(r[i]) for i in cols] for r in body[:n_frames]], dtype=np.float32)
    except (ValueError, IndexError) as exc:
        raise UserError(f"{path}: malformed row ({exc})") from None
    return {header[i]: vals[:, k] for k, i in enumerate(cols)}


def _video_fps(path: Path) -> float | None:
    import av

    try:
        with av.open(str(path)) as c:
            if not c.streams.video:
                return None
            r = c.streams.video[0].average_rate
            return float(r) if r else None
    except av.error.FFmpegError:
        raise UserError(f"{path}: not a readable video") from None


_FEATURE_FILES = {"ds": "aud_ds.npy", "hu": "aud_hu.npy", "eo": "aud_eo.npy", "wavlm": "aud_wavlm.npy"}


def _guess_feature_kind(a: np.ndarray) -> str | None:
    if a.ndim == 3 and a.shape[1:] == (16, 29):
        return "ds"
    if a.ndim == 3 and a.shape[1:] == (2, 1024) or a.ndim == 2 and a.shape[1] == 1024:
        return "hu"
    return None


def _read_features(root: Path, n: int, notes: list[str]) -> dict[str, np.ndarray]:
    feats: dict[str, np.ndarray] = {}
    for kind, fname in _FEATURE_FILES.items():
        p = root / fname
        if p.exists():
            feats[kind] = _load_feature(p, kind, n, notes)
    p = root / "aud.npy"
    if p.exists():
        a = np.load(p, mmap_mode="r")
        kind = _guess_feature_kind(a)
        if kind is None:
            notes.append(f"{p}: shape {a.shape} is neither DeepSpeech [N,16,29] nor HuBERT [N,2,1024]; ignored (rename it aud_ds.npy / aud_hu.npy)")
        elif kind not in feats:
            feats[kind] = _load_feature(p, kind, n, notes)
            notes.append(f"{p}: read as '{kind}' features from its shape {tuple(a.shape)}")
    return feats


def _load_feature(p: Path, kind: str, n: int, notes: list[str]) -> np.ndarray:
    try:
        a = np.load(p)
    except (ValueError, OSError) as exc:
        raise UserError(f"{p}: not a readable .npy file ({exc})") from None
    if kind == "ds" and a.shape[1:] != (16, 29):
        raise UserError(f"{p}: DeepSpeech features must be [N, 16, 29], got {a.shape}")
    if kind == "hu":
        if a.ndim == 2 and a.shape[1] == 1024:
            a = a.reshape(-1, 2, 1024)
            notes.append(f"{p}: [S, 1024] reshaped to [-1, 2, 1024] (two 50 Hz steps per frame)")
        if a.ndim != 3 or a.shape[1:] != (2, 1024):
            raise UserError(f"{p}: HuBERT features must be [N, 2, 1024], got {a.shape}")
    if a.shape[0] < n:
        raise UserError(f"{p}: {a.shape[0]} feature rows for {n} frames")
    if a.shape[0] > n:
        notes.append(f"{p}: {a.shape[0]} feature rows for {n} frames; the extra rows are ignored")
    a = np.asarray(a[:n], dtype=np.float32)
    if not np.all(np.isfinite(a)):
        raise UserError(f"{p}: contains non-finite values")
    return a


def check_jpegs(root: str | Path) -> int:
    """Check that every ``gt_imgs/<i>.jpg`` of a subject folder is a whole JPEG file, without decoding.

    A JPEG starts with the SOI marker and a marker segment (``FF D8 FF``) and ends with EOI
    (``FF D9``, possibly followed by padding zeros). A PNG renamed ``.jpg`` or a file cut short in a
    copy fails here, where :func:`read_subject` (which reads only the first frame's header) would pass it.

    Returns:
        The number of files checked.

    Raises:
        UserError: naming the first file that is not a whole JPEG.
    """
    gt_dir = Path(root) / "gt_imgs"
    files = sorted((p for p in gt_dir.glob("*.jpg") if p.stem.isdigit()), key=lambda p: int(p.stem))
    for p in files:
        with open(p, "rb") as f:
            head = f.read(3)
            f.seek(max(0, p.stat().st_size - 64))
            tail = f.read().rstrip(b"\0")
        if head != b"\xff\xd8\xff":
            raise UserError(f"{p}: not a JPEG file (it starts with {head.hex(' ') or 'nothing'}, not ff d8 ff)")
        if not tail.endswith(b"\xff\xd9"):
            raise UserError(f"{p}: JPEG file is cut short (no end-of-image marker); re-copy it")
    return len(files)


def read_subject(root: str | Path, name: str | None = None, *, check_images: bool = True, derive: bool = True) -> Subject:
    """Read a processed subject folder.

    Args:
        root: the subject folder (``data/<ID>``).
        name: subject name; the folder name by default.
        check_images: check that every ``gt_imgs/<i>.jpg`` exists (a directory listing,
            no decoding). The first frame's header gives the subject's size in any case.
        derive: where the folder has no ``lms3d.npy`` or no depth/normal maps, derive 3D
            landmarks and a head prior from its landmarks and cameras
            (:mod:`lmgs_eval.data.complete`; cached outside the folder, named in the notes).

    Raises:
        UserError: naming the file and what is wrong.
    """
    root = Path(root)
    if not root.is_dir():
        raise UserError(f"{root}: subject folder not found")
    name = name or root.name
    notes: list[str] = []
    top, train_frames, val_frames = _read_transforms(root)
    frames = train_frames + val_frames
    ids = [int(fr["img_id"]) for fr in frames]
    n = len(ids)
    if n == 0:
        raise UserError(f"{root}: transforms list no frames")
    if sorted(ids) != list(range(n)):
        raise UserError(f"{root}: transforms img_id values must be 0..{n - 1} once each (got {n} ids from {min(ids)} to {max(ids)})")
    order = np.argsort(ids)
    c2w = np.stack([np.asarray(frames[k]["transform_matrix"], np.float64) for k in order]).astype(np.float32)
    train_ids = np.asarray(sorted(int(f["img_id"]) for f in train_frames), dtype=np.int64)
    test_ids = np.asarray(sorted(int(f["img_id"]) for f in val_frames), dtype=np.int64)
    if val_frames and len(train_ids) != split_point(n):
        notes.append(f"{root}: split of the transforms files ({len(train_ids)} train / {len(test_ids)} test) differs from the first-10/11 convention; kept as given")
    if not val_frames:
        cut = split_point(n)
        train_ids, test_ids = np.arange(cut), np.arange(cut, n)
    if not len(train_ids) or not len(test_ids):
        raise UserError(f"{root}: {n} frame{'s' if n != 1 else ''}, split {len(train_ids)} train / {len(test_ids)} test: "
                        f"too few frames (a subject needs one to train on and one to test on: {MIN_SPLIT_FRAMES} or more "
                        "under the first-10/11 split)")

    # Images: all present; the first one's size (from its header) is the subject's size.
    gt_dir = root / "gt_imgs"
    if not gt_dir.is_dir():
        raise UserError(f"{gt_dir}: folder not found")
    if check_images:
        have = {p.name for p in gt_dir.iterdir()}
        miss = [i for i in range(n) if f"{i}.jpg" not in have]
        if miss:
            raise UserError(f"{gt_dir}: {len(miss)} of {n} frames listed in transforms are missing (first: {miss[0]}.jpg)")
        extra = sum(1 for h in have if h.endswith(".jpg") and h[:-4].isdigit() and int(h[:-4]) >= n)
        if extra:
            notes.append(f"{gt_dir}: {extra} images beyond the {n} frames of transforms are ignored")
    width, height = image_size(gt_dir / "0.jpg")
    focal = float(top["focal_len"])
    cx = float(top.get("cx", width / 2))
    cy = float(top.get("cy", height / 2))
    if not (np.isfinite(focal) and focal > 0):
        raise UserError(f"{root / 'transforms_train.json'}: focal_len must be positive, got {top['focal_len']}")

    lms = np.stack([_read_lms(root / "ori_imgs" / f"{i}.lms") for i in range(n)]).astype(np.float32)

    # Audio: 16 kHz mono, at least n * 640 samples.
    wav = root / "aud.wav"
    if not wav.exists():
        raise UserError(f"{wav}: audio file not found")
    audio, anotes = load_audio(wav)
    notes += anotes
    need = n * SAMPLES_PER_FRAME
    if len(audio) < need:
        short = need - len(audio)
        if short > SAMPLES_PER_FRAME:
            raise UserError(f"{wav}: audio is {len(audio) / SAMPLE_RATE:.2f} s, shorter than the {n} frames ({n / FPS:.2f} s)")
        audio = np.concatenate([audio, np.zeros(short, np.float32)])
        notes.append(f"{wav}: {short} samples of silence appended to cover the last frame")

    video = root / f"{root.name}.mp4"
    if video.exists():
        fps = _video_fps(video)
        if fps is not None and abs(fps - FPS) > 0.01:
            raise UserError(f"{video}: video is {fps:g} fps; the layout requires {FPS} fps (re-encode it, e.g. ffmpeg -r 25)")

    au_path = root / "au.csv"
    if au_path.exists():
        aus = read_au_csv(au_path, n)
        blink = aus["AU45_r"]
    else:
        aus, blink = {}, np.zeros(n, np.float32)
        notes.append(f"{au_path}: not found; blink (AU45_r) set to zero")

    feats = _read_features(root, n, notes)

    lms3d = None
    p3 = root / "lms3d.npy"
    if p3.exists():
        lms3d = np.load(p3).astype(np.float32)
        if lms3d.shape != (n, 68, 3):
            raise UserError(f"{p3}: expected [{n}, 68, 3], got {lms3d.shape}")

    meta = _read_json(root / "meta.json") if (root / "meta.json").exists() else {}
    head_prior = prior = None
    has_maps = (root / "depth").is_dir() and (root / "normal").is_dir()
    if derive and (lms3d is None or not has_maps):
        try:
            got3d, prior, cache = derive_priors(root, lms, c2w, focal, cx, cy)
        except (InputError, ValueError, np.linalg.LinAlgError) as exc:
            got3d = prior = None
            notes.append(f"{root}: no lms3d.npy or depth/normal maps, and none could be derived ({exc})")
    if derive and prior is not None:
        missing, what = [], []
        if lms3d is None:
            lms3d = got3d
            missing.append("lms3d.npy")
            what.append("3D landmarks (2D landmarks lifted on their camera rays with a generic face relief)")
        if not has_maps:
            head_prior = prior
            missing.append("depth/normal maps")
            what.append("depth / normal priors (a head ellipsoid placed on those landmarks, inside the head parsing mask)")
        notes.append(f"{root}: no {' or '.join(missing)}; derived {' and '.join(what)}, cached at {cache} ({prior.source})")
    return Subject(
        name=name,
        root=root,
        width=int(width),
        height=int(height),
        focal=focal,
        cx=cx,
        cy=cy,
        c2w=c2w,
        landmarks=lms,
        audio=audio,
        blink=np.asarray(blink, np.float32),
        aus=aus,
        train_ids=train_ids,
        test_ids=test_ids,
        landmarks3d=lms3d,
        audio_features=feats,
        bundled=bool(meta.get("bundled", False)),
        notes=tuple(notes),
        meta=meta,
        head_prior=head_prior,
    )
