"""The training corpus of the bundled SyncNet-style scorer: clips rendered by the bundled generator,
their face crops and MFCC windows, cached by recipe (see :mod:`lmgs_eval.metrics.sync.train.pixel`).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from lmgs_eval.metrics.sync import crops, maths, pixel
from lmgs_eval.metrics.sync.train.clips import cached_npz

FACES = ("astronaut", "hopper")
SIZES = (112, 128, 160)
HW = (48, 48)
REGION = "mouth"  # pixel.MOUTH_BOX of the 224 crop: the lower half of a dlib-box crop cuts through the mouth
CORPUS_FILE = Path(__file__).with_name("corpus.txt")
RECIPE_VERSION = "2"
SPEC_POOL = 160
N_ART = 5  # articulation.MOUTH: jaw, lip width, rounding, closure, lip-to-teeth


# ----------------------------------------------------------------------------- corpus
def heldout_voices() -> list[str]:
    from lmgs_eval.data.bundled.generator import CROSS

    return sorted({v for per in CROSS.values() for v, _ in per.values()})


def split() -> dict:
    """Training and held-out voices and texts (disjoint)."""
    from lmgs_eval.data.bundled import list_voices
    from lmgs_eval.data.bundled.generator import load_corpus, read_sections

    corpus = load_corpus()
    extra = read_sections(CORPUS_FILE)
    train_texts = list(corpus["train"]) + list(extra["train"])
    held_texts = list(corpus["cross-a"]) + list(corpus["cross-b"]) + list(extra["heldout"])
    hv = heldout_voices()
    voices = list_voices()
    train_voices = [v for v in voices if v not in hv]
    held_voices = [v for v in voices if v in hv]
    assert not set(train_texts) & set(held_texts)
    assert not set(train_voices) & set(held_voices)
    return {"train_texts": train_texts, "heldout_texts": held_texts, "train_voices": train_voices,
            "heldout_voices": held_voices}


def clip_specs(n_clips: int, seed: int, sp: dict) -> list[dict]:
    """Training clips: two sentences each, voices and faces balanced, sizes drawn.

    The list for ``n`` clips is the first ``n`` of the list for ``max(n, SPEC_POOL)``, so a smaller corpus reuses the cache.
    """
    want, n_clips = n_clips, max(n_clips, SPEC_POOL)
    rng = np.random.default_rng([seed, 1])
    texts, voices = sp["train_texts"], sp["train_voices"]
    order = np.concatenate([rng.permutation(len(texts)) for _ in range(2 * n_clips // len(texts) + 2)])
    vorder = np.concatenate([rng.permutation(len(voices)) for _ in range(n_clips // len(voices) + 2)])
    out = []
    for j in range(n_clips):
        t = [texts[order[2 * j]], texts[order[2 * j + 1]]]
        out.append({"id": f"train{j:04d}", "face": FACES[j % 2], "voice": voices[vorder[j]],
                    "text": " ".join(t), "size": int(SIZES[rng.integers(len(SIZES))]), "seed": seed * 100000 + j})
    return out[:want]


def heldout_specs(n_clips: int, sp: dict) -> list[dict]:
    """Held-out clips: held-out voices and texts, both faces, 128 and 256 px."""
    texts, voices = sp["heldout_texts"], sp["heldout_voices"]
    out = []
    for j in range(n_clips):
        t = [texts[(2 * j) % len(texts)], texts[(2 * j + 1) % len(texts)]]
        out.append({"id": f"held{j:03d}", "face": FACES[j % 2], "voice": voices[(j // 2) % len(voices)],
                    "text": " ".join(t), "size": (128, 256)[(j // 2) % 2], "seed": 900000 + j})
    return out


# ----------------------------------------------------------------------------- crops + mfcc
def prepare(crops224: np.ndarray) -> np.ndarray:
    """The scorer's own input preparation (``SyncScorer.prepare``), as uint8 0..255."""
    sc = pixel.SyncScorer("bundled-sync", None, "", HW, REGION, "bgr_0_1")
    return np.clip(np.rint(sc.prepare(crops224) * 255.0), 0, 255).astype(np.uint8)


def _augment_audio(audio: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    x = audio.astype(np.float64) * rng.uniform(0.25, 2.0)
    rms = float(np.sqrt(np.mean(x * x))) + 1e-8
    snr = rng.uniform(12.0, 40.0)
    x = x + rng.standard_normal(x.shape) * rms * 10 ** (-snr / 20)
    return np.clip(x, -1.0, 1.0)


def render_clip(spec: dict) -> dict:
    """Synthesize one clip; its ``lse()`` face boxes (plus a jittered copy) and MFCCs (clean + 2 augmented)."""
    from lmgs_eval.data.bundled import synthesize_clip

    clip = synthesize_clip(spec["face"], spec["text"], spec["voice"], size=spec["size"], seed=spec["seed"])
    boxes, n_missing = crops.face_boxes(clip.frames)  # uint8, as lse() reads a clip
    rng = np.random.default_rng([spec["seed"], 7])
    jb = boxes.copy()
    jb[:, 0] += boxes[:, 2] * rng.uniform(-0.06, 0.06)
    jb[:, 1] += boxes[:, 2] * rng.uniform(-0.06, 0.06)
    jb[:, 2] *= rng.uniform(0.92, 1.08)
    mf = [maths.mfcc_13(clip.audio)] + [maths.mfcc_13(_augment_audio(clip.audio, rng)) for _ in range(2)]
    return {"frames": clip.frames, "audio": clip.audio, "boxes": np.stack([boxes, jb]),
            "art": np.asarray(clip.articulation[:, :N_ART], np.float32),
            "mfcc": np.stack(mf).astype(np.float32), "n_samples": np.int64(len(clip.audio)),
            "n_missing": np.int64(n_missing)}


def cache_dir(meta: dict) -> Path:
    from lmgs_eval.data.bundled import GENERATOR_VERSION
    from lmgs_eval.paths import cache_root

    key = hashlib.sha256(json.dumps({**meta, "generator": GENERATOR_VERSION, "recipe": RECIPE_VERSION,
                                     "crop": [crops.CROP_SIZE, crops.CROP_SCALE, crops.PAD_VALUE, crops.SMOOTH_KERNEL]},
                                    sort_keys=True).encode()).hexdigest()[:16]
    return cache_root() / "sync_train" / key


def _build_one(args) -> str:
    return cached_npz(*args, render_clip)


def build_cache(specs: list[dict], folder: Path, workers: int, desc: str) -> list[Path]:
    from tqdm import tqdm

    folder.mkdir(parents=True, exist_ok=True)
    jobs = [(s, str(folder)) for s in specs]
    out = []
    if workers > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(workers) as pool:
            for p in tqdm(pool.imap(_build_one, jobs), total=len(jobs), desc=desc, unit="clip"):
                out.append(Path(p))
    else:
        for j in tqdm(jobs, desc=desc, unit="clip"):
            out.append(Path(_build_one(j)))
    return out


def load_clip(path: Path, keep_frames: bool = False) -> dict:
    """A cached clip with its scorer inputs: ``video [2, T, H, W, 3]`` uint8 (exact and jittered boxes), audio windows."""
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    prep = Path(path).with_name(f"{Path(path).stem}.{REGION}{HW[0]}x{HW[1]}.npy")
    if prep.is_file():
        d["video"] = np.load(prep)
    else:
        d["video"] = np.stack([prepare(crops.crop_faces(d["frames"], b)) for b in d["boxes"]])
        tmp = prep.with_name(f"{prep.stem}.{os.getpid()}.tmp.npy")
        np.save(tmp, d["video"])
        tmp.replace(prep)
    if not keep_frames:
        del d["frames"], d["audio"]
    n = d["video"].shape[1]
    last = min(n, int(d["n_samples"]) // maths.SAMPLES_PER_FRAME) - 5
    m = d["mfcc"]  # [3, 13, M]
    aw = np.zeros((m.shape[0], max(last, 0), 13, 20), np.float32)
    for i in range(max(last, 0)):
        seg = m[:, :, 4 * i:4 * i + 20]
        aw[:, i, :, :seg.shape[2]] = seg
    d["awin"] = aw
    d["last"] = last
    return d


