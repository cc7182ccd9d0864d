"""Looking at a bundled subject: a short preview video with sound and a contact sheet."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lmgs.lips import lip_gap
from lmgs_eval.data.audio import load_audio
from lmgs_eval.data.images import read_rgb_u8, write_rgb
from lmgs_eval.data.video import write_video
from lmgs_eval.errors import UserError


def make_preview(subject_dir: Path, out_mp4: Path, max_seconds: float = 10.0) -> Path:
    """Write the first ``max_seconds`` of a subject (``gt_imgs`` + ``aud.wav``) as an mp4 with sound."""
    root = Path(subject_dir)
    gt = root / "gt_imgs"
    if not gt.is_dir():
        raise UserError(f"{gt}: folder not found (not a processed subject)")
    n = len([p for p in gt.iterdir() if p.suffix == ".jpg"])
    k = min(n, int(round(max_seconds * 25)))
    if k == 0:
        raise UserError(f"{gt}: no frames")
    frames = np.stack([read_rgb_u8(gt / f"{i}.jpg") for i in range(k)])
    audio, _ = load_audio(root / "aud.wav")
    write_video(Path(out_mp4), frames, 25, audio[: k * 640])
    return Path(out_mp4)


def _pick(root: Path, n: int) -> list[tuple[int, str]]:
    art = np.load(root / "articulation.npy")
    meta = json.loads((root / "meta.json").read_text())
    cols = meta["articulation_columns"]
    lms = np.stack([np.loadtxt(root / "ori_imgs" / f"{i}.lms") for i in range(n)])
    gap = lip_gap(lms)
    phones = json.loads((root / "phonemes.json").read_text())
    chosen: list[tuple[int, str]] = []

    def add(order, label, k=4, spacing=12):
        for i in order:
            i = int(i)
            if len([c for c in chosen if c[1] == label]) >= k:
                break
            if all(abs(i - j) >= spacing for j, _ in chosen):
                chosen.append((i, label))

    add(np.argsort(-gap), "open")
    pbm = [int((p["start"] + p["end"]) / 2 * 25) for p in phones if p["viseme"] == "PP" and p["end"] - p["start"] > 0.05]
    add([i for i in pbm if i < n], "p/b/m")
    add(np.argsort(-art[:, cols.index("blink")]), "blink")
    pose = np.abs(art[:, cols.index("yaw")]) + np.abs(art[:, cols.index("pitch")])
    add(np.argsort(-pose), "pose")
    return sorted(chosen)[:16]


def contact_sheet(subject_dir: Path, out_png: Path, *, with_landmarks: bool = True) -> Path:
    """A 4x4 grid of frames (widest mouth, p/b/m closures, blinks, largest head turns),
    each labelled with its index and why it was picked; ground-truth mouth landmarks drawn."""
    import cv2

    root = Path(subject_dir)
    n = len(list((root / "gt_imgs").glob("*.jpg")))
    picks = _pick(root, n)
    tiles = []
    for i, label in picks:
        img = read_rgb_u8(root / "gt_imgs" / f"{i}.jpg")  # drawn on in RGB: the colours below are grey or green
        s = img.shape[0]
        if s < 256:
            img = cv2.resize(img, (256, 256), interpolation=cv2.INTER_NEAREST)
        f = img.shape[0] / s
        if with_landmarks:
            for x, y in np.loadtxt(root / "ori_imgs" / f"{i}.lms")[48:68]:
                cv2.circle(img, (int(x * f), int(y * f)), 1, (0, 255, 0), -1)
        cv2.putText(img, f"{i} {label}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 2, cv2.LINE_AA)
        cv2.putText(img, f"{i} {label}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    while len(tiles) < 16:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[r * 4 : r * 4 + 4], 1) for r in range(4)]
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_rgb(out, np.concatenate(rows, 0))
    return out
