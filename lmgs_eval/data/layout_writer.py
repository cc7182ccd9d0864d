"""Writing the layout's small files: JSON, landmarks, transforms, ``track_params.pt``, ``au.csv``, file hashes.

What :mod:`lmgs_eval.data.layout` reads, written alike by the bundled generator and the ingest
(fixed formats, sorted keys, no timestamps: the same input gives the same bytes).
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from lmgs.fileio import sha256_file
from lmgs_eval.data.layout import split_point
from lmgs_eval.data.subject import FPS


def write_json(path: Path, obj) -> None:
    Path(path).write_text(json.dumps(obj, indent=1, sort_keys=True) + "\n", encoding="utf-8")


def write_lms(path: Path, lms: np.ndarray) -> None:
    Path(path).write_text("".join(f"{x:.4f} {y:.4f}\n" for x, y in lms), encoding="ascii")


def transforms(c2w: np.ndarray, ids, focal: float, w: int, h: int) -> dict:
    """A transforms file's content: the focal length, the principal point at the frame centre, and the
    camera-to-world matrix (``transform_matrix``) of each frame of ``ids``."""
    return {"focal_len": float(focal), "cx": float(w / 2), "cy": float(h / 2),
            "frames": [{"img_id": int(i), "aud_id": int(i), "transform_matrix": np.asarray(c2w[i]).tolist()} for i in ids]}


def write_transforms(root: Path, c2w: np.ndarray, focal: float, w: int, h: int) -> None:
    """``transforms_train.json`` (first ``int(n * 10 / 11)`` frames) and ``transforms_val.json``."""
    n = len(c2w)
    cut = split_point(n)
    write_json(Path(root) / "transforms_train.json", transforms(c2w, range(cut), focal, w, h))
    write_json(Path(root) / "transforms_val.json", transforms(c2w, range(cut, n), focal, w, h))


def write_track_params(path: Path, euler: np.ndarray, trans: np.ndarray, focal: float) -> None:
    """ER-NeRF's ``track_params.pt`` fields a landmark fit has: ``euler`` (pitch, yaw, roll, radians),
    ``trans`` (metres) ``[N, 3]`` and ``focal`` ``[1]``; no ``id``/``exp`` (no 3DMM)."""
    import torch

    buf = io.BytesIO()
    torch.save({"euler": torch.from_numpy(np.asarray(euler, np.float32)), "trans": torch.from_numpy(np.asarray(trans, np.float32)),
                "focal": torch.tensor([focal], dtype=torch.float32)}, buf)
    Path(path).write_bytes(buf.getvalue())


def write_au_csv(path: Path, aus: dict[str, np.ndarray], found: np.ndarray, columns: tuple[str, ...]) -> None:
    """OpenFace's CSV layout (", " separated, so the AU columns read with a leading space): the ``columns``
    of ``aus``, per frame; ``found``: the frames with a face (confidence 0.98, success 1; else 0)."""
    n = len(found)
    cols = ["frame", "face_id", "timestamp", "confidence", "success", *columns]
    lines = [", ".join(cols)]
    for i in range(n):
        ok = bool(found[i])
        vals = [str(i + 1), "0", f"{i / FPS:.3f}", "0.98" if ok else "0.00", "1" if ok else "0"]
        lines.append(", ".join(vals + [f"{aus[c][i]:.2f}" for c in columns]))
    Path(path).write_text("\n".join(lines) + "\n", encoding="ascii")


def file_hashes(folder: Path, skip: tuple[str, ...] = ("manifest.json",)) -> dict[str, str]:
    """sha256 of every file under ``folder`` by relative path (except ``skip``)."""
    folder = Path(folder)
    return {p.relative_to(folder).as_posix(): sha256_file(p) for p in sorted(folder.rglob("*")) if p.is_file() and p.name not in skip}
