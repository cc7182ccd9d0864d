"""Writing the layout's small files: landmarks, transforms, track_params, au.csv, the manifest."""

from __future__ import annotations

import io as _io
import json
from pathlib import Path

import numpy as np

from lmgs.fileio import sha256_file
from lmgs_eval.data.layout import split_point

FPS = 25
AU_COLUMNS = ("AU25_r", "AU26_r", "AU45_r")


def write_json(path: Path, obj) -> None:
    Path(path).write_text(json.dumps(obj, indent=1, sort_keys=True) + "\n", encoding="utf-8")


def write_lms(path: Path, lms: np.ndarray) -> None:
    Path(path).write_text("".join(f"{x:.4f} {y:.4f}\n" for x, y in lms), encoding="ascii")


def write_transforms(root: Path, c2w: np.ndarray, focal: float, w: int, h: int) -> None:
    """``transforms_train.json`` (first ``int(n * 10 / 11)`` frames) and ``transforms_val.json``."""
    n = len(c2w)
    cut = split_point(n)

    def part(ids):
        return {"focal_len": float(focal), "cx": float(w / 2), "cy": float(h / 2),
                "frames": [{"img_id": int(i), "aud_id": int(i), "transform_matrix": np.asarray(c2w[i]).tolist()} for i in ids]}

    write_json(root / "transforms_train.json", part(range(cut)))
    write_json(root / "transforms_val.json", part(range(cut, n)))


def write_track_params(path: Path, euler: np.ndarray, trans: np.ndarray, focal: float) -> None:
    """ER-NeRF's ``track_params.pt`` fields this fit has: ``euler`` (pitch, yaw, roll, radians),
    ``trans`` (metres) ``[N, 3]`` and ``focal`` ``[1]``; no ``id``/``exp`` (no 3DMM)."""
    import torch

    buf = _io.BytesIO()
    torch.save({"euler": torch.from_numpy(np.asarray(euler, np.float32)), "trans": torch.from_numpy(np.asarray(trans, np.float32)),
                "focal": torch.tensor([focal], dtype=torch.float32)}, buf)
    Path(path).write_bytes(buf.getvalue())


def eye_openness(lms: np.ndarray) -> np.ndarray:
    """Eye aspect ratio ``[N]`` (Soukupova & Cech 2016), mean of both eyes:

    .. math:: \\mathrm{EAR} = \\frac{|p_{2}-p_{6}| + |p_{3}-p_{5}|}{2\\,|p_{1}-p_{4}|}
    """

    def ear(e):
        a = np.linalg.norm(e[:, 1] - e[:, 5], axis=1) + np.linalg.norm(e[:, 2] - e[:, 4], axis=1)
        return a / (2 * np.linalg.norm(e[:, 0] - e[:, 3], axis=1) + 1e-9)

    return 0.5 * (ear(lms[:, 36:42]) + ear(lms[:, 42:48]))


def action_units(lms: np.ndarray) -> dict[str, np.ndarray]:
    """Stand-ins for OpenFace's intensities (0-5) from the 2D landmarks, per frame.

    * ``AU45_r`` (blink): ``5 * (1 - EAR / EAR_open)`` clipped to [0, 5], where ``EAR_open`` is
      the clip's 90th percentile of the eye aspect ratio (the eyes' usual openness).
    * ``AU25_r`` (lips part): inner-lip gap (62-66) over the mouth width (60-64), x 10, clipped.
    * ``AU26_r`` (jaw drop): the nose-to-chin distance (33-8) above its 10th percentile, over
      the face height, x 25, clipped.
    OpenFace fits appearance models; these read geometry only, and are named so in the manifest.
    """
    ear = eye_openness(lms)
    open_ = max(float(np.percentile(ear, 90)), 1e-6)
    au45 = np.clip(5.0 * (1.0 - ear / open_), 0, 5)
    gap = np.linalg.norm(lms[:, 62] - lms[:, 66], axis=1) / (np.linalg.norm(lms[:, 60] - lms[:, 64], axis=1) + 1e-9)
    au25 = np.clip(10.0 * gap, 0, 5)
    fh = np.linalg.norm(lms[:, 8] - lms[:, 27], axis=1) + 1e-9
    jaw = np.linalg.norm(lms[:, 8] - lms[:, 33], axis=1) / fh
    au26 = np.clip(25.0 * (jaw - np.percentile(jaw, 10)), 0, 5)
    return {"AU25_r": au25, "AU26_r": au26, "AU45_r": au45}


def write_au_csv(path: Path, aus: dict[str, np.ndarray], found: np.ndarray) -> None:
    """OpenFace's CSV layout (", " separated, so the AU columns read with a leading space)."""
    n = len(found)
    cols = ["frame", "face_id", "timestamp", "confidence", "success", *AU_COLUMNS]
    lines = [", ".join(cols)]
    for i in range(n):
        ok = bool(found[i])
        vals = [str(i + 1), "0", f"{i / FPS:.3f}", "0.98" if ok else "0.00", "1" if ok else "0"]
        lines.append(", ".join(vals + [f"{aus[c][i]:.2f}" for c in AU_COLUMNS]))
    Path(path).write_text("\n".join(lines) + "\n", encoding="ascii")


def file_hashes(folder: Path, skip: tuple[str, ...] = ("manifest.json",)) -> dict[str, str]:
    """sha256 of every file under ``folder`` by relative path (except ``skip``)."""
    folder = Path(folder)
    return {p.relative_to(folder).as_posix(): sha256_file(p) for p in sorted(folder.rglob("*")) if p.is_file() and p.name not in skip}


def tool_versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {}
    for pkg in ("lmgs", "dlib", "opencv-contrib-python-headless", "opencv-python-headless", "opencv-python", "av", "numpy", "scipy", "torch"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            continue
    try:
        import cv2

        out["cv2"] = cv2.__version__
    except ImportError:
        pass
    return out
