"""A contact sheet of an ingested subject, to see at a glance whether the ingest worked.

Ten frames spread over the clip, each with the 68 landmarks (green), the head mask's outline
(red), the neck and torso outline (blue) and the head's axes from the fitted pose (x red,
y green, z blue, 5 cm long at the template's origin); then the plate ``bc.jpg`` and one
parsing map. A landmark off the face, a mask that cuts the hair or swallows the background,
axes that do not turn with the head, or a plate with a ghost of the person show here.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lmgs_eval.data.images import read_rgb_u8, write_rgb
from lmgs_eval.errors import UserError

AXIS_M = 0.05


def _outline(img: np.ndarray, mask: np.ndarray, colour) -> None:
    import cv2

    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(img, cs, -1, colour, 1, cv2.LINE_AA)


def _axes(img: np.ndarray, c2w: np.ndarray, focal: float, cx: float, cy: float) -> None:
    import cv2

    w2c = np.linalg.inv(c2w @ np.diag([1.0, -1.0, -1.0, 1.0]))
    pts = np.array([[0, 0, 0], [AXIS_M, 0, 0], [0, AXIS_M, 0], [0, 0, AXIS_M]], np.float64)
    pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    uv = np.stack([focal * pc[:, 0] / pc[:, 2] + cx, focal * pc[:, 1] / pc[:, 2] + cy], 1)
    o = tuple(int(round(v)) for v in uv[0])
    for k, col in zip((1, 2, 3), ((255, 0, 0), (0, 255, 0), (0, 0, 255))):
        cv2.line(img, o, tuple(int(round(v)) for v in uv[k]), col, 2, cv2.LINE_AA)


def contact_sheet(subject_dir: str | Path, out_png: str | Path, *, tiles: int = 10, tile: int = 256) -> Path:
    """Write the contact sheet of ``subject_dir`` to ``out_png`` (a 4-column grid)."""
    import cv2

    root = Path(subject_dir)
    tr = [json.loads((root / f).read_text()) for f in ("transforms_train.json", "transforms_val.json")]
    frames = sorted(tr[0]["frames"] + tr[1]["frames"], key=lambda f: f["img_id"])
    if not frames:
        raise UserError(f"{root}: no frames in the transforms files")
    focal, cx, cy = float(tr[0]["focal_len"]), float(tr[0]["cx"]), float(tr[0]["cy"])
    n = len(frames)
    ids = np.linspace(0, n - 1, min(tiles, n)).round().astype(int)
    out = []
    for i in ids:
        img = read_rgb_u8(root / "ori_imgs" / f"{i}.jpg").copy()
        lms = np.loadtxt(root / "ori_imgs" / f"{i}.lms")
        p = read_rgb_u8(root / "parsing" / f"{i}.png")
        _outline(img, np.all(p == (255, 0, 0), axis=-1), (255, 40, 40))
        _outline(img, np.all(p == (0, 255, 0), axis=-1) | np.all(p == (0, 0, 255), axis=-1), (60, 120, 255))
        s = max(1, round(img.shape[0] / 256))
        for x, y in lms:
            cv2.circle(img, (int(round(x - 0.5)), int(round(y - 0.5))), s, (0, 255, 0), -1, cv2.LINE_AA)
        _axes(img, np.asarray(frames[i]["transform_matrix"], np.float64), focal, cx, cy)
        out.append((img, f"frame {i}"))
    try:
        import torch

        euler = np.degrees(torch.load(root / "track_params.pt", weights_only=True)["euler"].numpy())
    except (OSError, RuntimeError, KeyError):
        euler = None
    if euler is not None:
        out = [(im, f"{lab}  p{euler[i, 0]:+.0f} y{euler[i, 1]:+.0f} r{euler[i, 2]:+.0f}") for (im, lab), i in zip(out, ids)]
    out.append((read_rgb_u8(root / "bc.jpg"), "plate bc.jpg"))
    out.append((read_rgb_u8(root / "parsing" / f"{ids[len(ids) // 2]}.png"), f"parsing {ids[len(ids) // 2]}"))
    cols = 4
    rows = (len(out) + cols - 1) // cols
    sheet = np.full((rows * tile, cols * tile, 3), 32, np.uint8)
    for k, (im, label) in enumerate(out):
        t = cv2.resize(im, (tile, tile), interpolation=cv2.INTER_AREA)
        cv2.putText(t, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(t, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
        r, c = divmod(k, cols)
        sheet[r * tile : (r + 1) * tile, c * tile : (c + 1) * tile] = t
    out_png = Path(out_png)
    write_rgb(out_png, sheet)
    return out_png
