"""What the ingest writes beside the layout's files (:mod:`lmgs_eval.data.layout_writer`): action units
from the landmarks, the tools' versions for the manifest, the work folder's arrays."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lmgs.fileio import atomic_path
from lmgs.lips import lip_gap

AU_COLUMNS = ("AU25_r", "AU26_r", "AU45_r")


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
    gap = lip_gap(lms) / (np.linalg.norm(lms[:, 60] - lms[:, 64], axis=1) + 1e-9)
    au25 = np.clip(10.0 * gap, 0, 5)
    fh = np.linalg.norm(lms[:, 8] - lms[:, 27], axis=1) + 1e-9
    jaw = np.linalg.norm(lms[:, 8] - lms[:, 33], axis=1) / fh
    au26 = np.clip(25.0 * (jaw - np.percentile(jaw, 10)), 0, 5)
    return {"AU25_r": au25, "AU26_r": au26, "AU45_r": au45}


def tool_versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {}
    for pkg in ("lmgs", "dlib", "opencv-contrib-python-headless", "opencv-python-headless", "opencv-python", "av", "numpy", "scipy", "torch", "onnxruntime", "ai-edge-litert"):
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


def save_npz(path: Path, **arrays) -> None:
    """Arrays into an ``.npz`` file, written through a temporary file and a rename."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
