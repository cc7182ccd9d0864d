"""Train the landmark sync scorer (``weights/landmark_sync.{onnx,json}``).

``python -m lmgs_eval.metrics.sync.train.landmark --out lmgs_eval/metrics/sync/weights`` (the defaults made the
shipped weights: 320 clips, 15-frame windows, 3500 steps, seed 0, 2 threads; about 26 minutes on 2 shared cores)

Recipe (deterministic for a seed and thread count; recorded in ``landmark_sync.json``):

* **Corpus.** Mouth trajectories made by the bundled generator's own parts, without
  rasterising: speech (``speech.synthesize``, two sentences from the ``[train]`` texts of
  ``corpus.txt`` and ``sync/train/corpus.txt``), articulation (``articulation.articulation``) and
  the head model's deformation and camera (``HeadModel.deform``, ``HeadModel.c2w``)
  projected like ``HeadModel.render``: the ground-truth 68 landmarks of each frame. Both
  faces, frame sizes 128-512. Voices: every espeak-ng voice except the held-out ones
  (``pixel_data.heldout_voices`` minus piper's ``joe``) plus piper's ``joe`` on training
  texts only: it is the only neural voice here, the closest to real speech.
* **Pose and articulation jitter** per clip: head yaw, pitch, roll and translation x1-4 of
  the generator's, mouth articulation (jaw, width, rounding) x0.6-1.5.
* **Landmark noise for the detector gap** (each clip three times, three draws): rigid
  jitter of the whole face per frame (translation 0-2 %, scale 0-2 % of the inter-ocular
  distance), white noise per point 0-4 %, slow (5-frame smoothed) noise per point 0-3 %,
  a 3-tap temporal smoothing with probability 0.3, 0-5 % of frames dropped (filled by
  interpolation as at scoring time), mouth motion that speech does not explain (three
  1-second smoothed components in random directions, 0-5 %), and the mouth's x and y motion
  scaled apart (x0.6-1.6 each). Real dlib landmarks jitter, lag and under-shoot; the
  generator's are exact.
* **Audio**: the clean MFCC and two noisy copies per clip (white noise at 5-40 dB SNR, a
  one-pole low-pass at 2-8 kHz or none, and vocal tract length perturbation: the mel
  filterbank's frequency axis scaled by 0.85-1.18, :func:`warped_mfcc`), then the scorer's
  per-clip normalisation.
* **Objective**: for every video window of a batch, the audio windows of its own clip at
  shifts -15..15 and all windows of the other clips: cross-entropy over ``-4 * distance``
  (the true window must be nearest, which puts the minimum of SyncNet's mean distance on
  the true offset) plus, from 30 % of the steps, a contrastive term (margin 2) on the L2
  distance with negatives at shifts of 3 or more frames and other clips; for the first 60 %
  of the steps (weight 1 decaying to 0) a linear head, not exported, regresses from the audio
  embedding the mouth features of the 5 frames in sync with it, so the audio branch learns
  mouth shape from the start.
* **Held-out acceptance** (``--heldout``): clips rendered in full by ``synthesize_clip`` with
  held-out texts and voices, landmarks from dlib on the frames (as every user's footage),
  scored through the public ``scoring.lse``: offset on synced audio, injected shifts of -10,
  -5, -3, 3, 5, 10 frames, LSE-C with another clip's audio.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np

from lmgs_eval.metrics.sync import maths, scorers, scoring
from lmgs_eval.metrics.sync.probe import shifted
from lmgs_eval.metrics.sync.train.clips import cached_npz
from lmgs_eval.metrics.sync import landmark as L

FACES = ("astronaut", "hopper")
SIZES = (128, 256, 512)
RECIPE_VERSION = "3"  # features and training
CORPUS_VERSION = "2"  # the rendered trajectories (speech, articulation jitter, projection)
N_VARIANTS = 3
SHIFTS = (-10, -5, -3, 3, 5, 10)


def split() -> dict:
    """Training and held-out voices and texts; piper's joe speaks training texts only."""
    from lmgs_eval.metrics.sync.train.pixel_data import split as pixel_split

    sp = pixel_split()
    joe = [v for v in sp["heldout_voices"] if v.startswith("piper:")]
    sp["train_voices"] = list(sp["train_voices"]) + joe
    return sp


def clip_specs(n: int, seed: int, sp: dict) -> list[dict]:
    rng = np.random.default_rng([seed, 11])
    texts, voices = sp["train_texts"], sp["train_voices"]
    out = []
    for j in range(n):
        t = rng.choice(len(texts), 2, replace=False)
        out.append({"id": f"lm{j:04d}", "face": FACES[j % 2], "voice": voices[j % len(voices)],
                    "text": " ".join(texts[k] for k in t), "size": int(SIZES[rng.integers(len(SIZES))]),
                    "seed": seed * 100000 + j})
    return out


def heldout_specs(n: int, sp: dict) -> list[dict]:
    from lmgs_eval.metrics.sync.train.pixel_data import heldout_specs as pixel_heldout

    return pixel_heldout(n, sp)


# ----------------------------------------------------------------------------- corpus
def project_landmarks(head, art: np.ndarray) -> np.ndarray:
    """Ground-truth ``[T, 68, 2]`` pixels for articulation rows, as ``HeadModel.render`` projects them."""
    from lmgs_eval.data.bundled.head import _GL_TO_CV

    out = np.empty((len(art), 68, 2))
    s, f = head.size, head.focal
    for i, a in enumerate(art):
        v = head.deform(a)[:68]
        w2c = np.linalg.inv(head.c2w(a) @ _GL_TO_CV)
        pc = v @ w2c[:3, :3].T + w2c[:3, 3]
        out[i] = np.stack([f * pc[:, 0] / pc[:, 2] + s / 2, f * pc[:, 1] / pc[:, 2] + s / 2], 1)
    return out


def make_clip(spec: dict) -> dict:
    """Speech, jittered articulation and ground-truth landmarks of one training clip."""
    from lmgs_eval.data.bundled import articulation as am
    from lmgs_eval.data.bundled import speech as spm
    from lmgs_eval.data.bundled.generator import FPS, SPF, head_model

    speech = spm.synthesize([spec["text"]], spec["voice"])
    n = int(np.ceil(speech.seconds * FPS))
    speech = spm.fit_length(speech, n * SPF)
    rng = np.random.default_rng([spec["seed"], 3])
    art = am.articulation(speech.phones, n, FPS, rng).astype(np.float64)
    cols = am.COLUMNS
    for c in ("yaw", "pitch", "roll", "tx", "ty", "tz"):
        art[:, cols.index(c)] *= rng.uniform(1.0, 4.0)
    for c in ("jaw", "lip_width", "lip_round"):
        art[:, cols.index(c)] *= rng.uniform(0.6, 1.5)
    lms = project_landmarks(head_model(spec["face"], spec["size"]), art)
    return {"lms": lms, "audio": speech.audio.astype(np.float32)}


def _cache_key(specs: list[dict]) -> str:
    from lmgs_eval.data.bundled import GENERATOR_VERSION

    return hashlib.sha256(json.dumps({"specs": specs, "gen": GENERATOR_VERSION, "recipe": CORPUS_VERSION},
                                     sort_keys=True).encode()).hexdigest()[:16]


def _build_one(args) -> str:
    return cached_npz(*args, make_clip)


def build_corpus(specs: list[dict], folder: Path, workers: int) -> list[Path]:
    from tqdm import tqdm

    folder.mkdir(parents=True, exist_ok=True)
    # grouped by head model (generator.head_model keeps only a few in memory; each takes seconds to build)
    jobs = [(s, str(folder)) for s in sorted(specs, key=lambda s: (s["face"], s["size"]))]
    if workers > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(workers) as pool:
            for _ in tqdm(pool.imap(_build_one, jobs, chunksize=8), total=len(jobs), desc="corpus", unit="clip"):
                pass
    else:
        for j in tqdm(jobs, desc="corpus", unit="clip"):
            _build_one(j)
    return [Path(_build_one((s, str(folder)))) for s in specs]  # in spec order; every file exists now


# ----------------------------------------------------------------------------- augmentation
def noisy_landmarks(lms: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The detector-gap augmentation of the recipe (module doc) on ``[T, 68, 2]`` pixels."""
    from scipy.ndimage import uniform_filter1d

    t = len(lms)
    iod = float(np.median(np.linalg.norm(lms[:, 45] - lms[:, 36], axis=1)))
    x = lms.copy()
    c = x.mean(1, keepdims=True)
    x = c + (x - c) * (1 + rng.uniform(0, 0.02) * rng.standard_normal((t, 1, 1)))
    x += rng.uniform(0, 0.02) * iod * rng.standard_normal((t, 1, 2))
    x += rng.uniform(0, 0.04) * iod * rng.standard_normal(x.shape)
    slow = uniform_filter1d(rng.standard_normal(x.shape), 5, axis=0) * np.sqrt(5)
    x += rng.uniform(0, 0.03) * iod * slow
    # mouth motion that speech does not explain (smiles, pursing): three slow (about 1 s) components mixed
    # into the 20 mouth points with random directions
    comp = uniform_filter1d(rng.standard_normal((t, 3)), 25, axis=0) * 5.0
    x[:, 48:68] += rng.uniform(0, 0.05) * iod * np.einsum("tc,cpk->tpk", comp, rng.standard_normal((3, 20, 2)))
    # people (and detectors) move the lips' x and y by different amounts
    m = x[:, 48:68] - x[:, 48:68].mean(0)
    x[:, 48:68] += m * (rng.uniform(0.6, 1.6, 2) - 1.0)
    if rng.random() < 0.3:
        x = uniform_filter1d(x, 3, axis=0)
    drop = rng.random(t) < rng.uniform(0, 0.05)
    drop[0] = False
    x[drop] = np.nan
    return L.fill_missing(x)[0]


def noisy_audio(audio: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    from scipy.signal import lfilter

    x = audio.astype(np.float64)
    rms = float(np.sqrt(np.mean(x * x))) + 1e-8
    x = x + rng.standard_normal(x.shape) * rms * 10 ** (-rng.uniform(5, 40) / 20)
    if rng.random() < 0.5:
        a = np.exp(-2 * np.pi * rng.uniform(2000, 8000) / 16000)
        x = lfilter([1 - a], [1, -a], x)
    return np.clip(x, -1, 1)


def warped_mfcc(audio: np.ndarray, alpha: float) -> np.ndarray:
    """``maths.mfcc_13`` with the mel filterbank's frequency axis scaled by ``alpha`` (vocal tract length
    perturbation): the same 400-sample frames every 160 samples, the filters placed as for a rate of ``16000 alpha``."""
    import python_speech_features

    x = np.clip(np.rint(np.asarray(audio, np.float64) * 32768.0), -32768, 32767)
    sr = 16000.0 * alpha
    return np.asarray(python_speech_features.mfcc(x, sr, winlen=400 / sr, winstep=160 / sr), np.float64).T


def load_clip(path: Path, seed: int, highpass: int = 0) -> dict | None:
    """A corpus clip as scorer inputs: mouth features ``feat [3, T, 40]`` (three noise draws) and normalised MFCCs
    ``mfcc [3, 13, M]`` (clean + two augmented copies); cached beside the clip (the draws are seeded by the seed
    and the clip's file name)."""
    path = Path(path)
    cached = path.with_name(f"{path.stem}.feat-r{RECIPE_VERSION}-s{seed}-hp{highpass}.npz")
    if cached.is_file():
        with np.load(cached) as z:
            return {"feat": z["feat"], "mfcc": z["mfcc"], "last": int(z["last"])}
    with np.load(path) as z:
        lms, audio = z["lms"], z["audio"]
    last = min(len(lms), len(audio) // maths.SAMPLES_PER_FRAME) - 5
    if last < 8:
        return None
    rng = np.random.default_rng([seed, int(hashlib.sha256(path.name.encode()).hexdigest()[:8], 16)])
    feat = np.stack([L.mouth_features(noisy_landmarks(lms, rng), highpass) for _ in range(N_VARIANTS)])
    mf = [L.audio_features(maths.mfcc_13(audio))]
    mf += [L.audio_features(warped_mfcc(noisy_audio(audio, rng), rng.uniform(0.85, 1.18))) for _ in range(N_VARIANTS - 1)]
    m = min(x.shape[1] for x in mf)
    d = {"feat": feat, "mfcc": np.stack([x[:, :m] for x in mf]), "last": last}
    tmp = cached.with_name(f"{cached.stem}.{os.getpid()}.tmp.npz")
    np.savez(tmp, **d)
    tmp.replace(cached)
    return d


# ----------------------------------------------------------------------------- training
def batch(clips: list[dict], rng: np.random.Generator, n_seg: int, seg_len: int, context: int = 5,
          vshift: int = maths.VSHIFT):
    """Video windows of a few clip segments, the audio windows around them, each pair's shift (10**6: other
    clip), and the mouth features in sync with each audio window (the auxiliary target)."""
    picks = rng.choice(len(clips), size=min(n_seg, len(clips)), replace=False)
    vids, auds, a_tgt, v_clip, v_pos, a_clip, a_idx = [], [], [], [], [], [], []
    for s, c in enumerate(picks):
        d = clips[c]
        last = d["last"]
        n = min(seg_len, last)
        i0 = int(rng.integers(0, last - n + 1))
        v = L.video_windows(d["feat"][rng.integers(len(d["feat"]))], last, context)
        a = L.audio_windows(d["mfcc"][rng.integers(len(d["mfcc"]))], last, context)
        vids.append(v[i0:i0 + n])
        v_clip += [s] * n
        v_pos += list(range(i0, i0 + n))
        lo, hi = max(0, i0 - vshift), min(last, i0 + n + vshift)
        auds.append(a[lo:hi])
        c0 = (context - 5) // 2
        a_tgt.append(v[lo:hi, :, c0:c0 + 5])
        a_clip += [s] * (hi - lo)
        a_idx += list(range(lo, hi))
    v_clip, v_pos, a_clip, a_idx = map(np.asarray, (v_clip, v_pos, a_clip, a_idx))
    shift = np.where(v_clip[:, None] == a_clip[None, :], a_idx[None, :] - v_pos[:, None], 10**6)
    return np.concatenate(vids), np.concatenate(auds), shift, np.concatenate(a_tgt)


def loss_fn(a_emb, v_emb, shift, w_con: float, margin: float = 2.0, scale: float = 4.0):
    import torch

    d = torch.cdist(v_emb, a_emb) + 1e-6
    sh = torch.as_tensor(shift)
    pos = sh == 0
    neg = (sh.abs() >= 3)
    logits = -scale * d
    target = pos.float().argmax(dim=1)
    ce = torch.nn.functional.cross_entropy(logits, target)
    con = (d[pos] ** 2).mean() + (torch.relu(margin - d[neg]) ** 2).mean()
    acc = float((logits.argmax(dim=1) == target).float().mean())
    return ce + w_con * con, {"ce": float(ce.detach()), "con": float(con.detach()), "acc": acc}


def train(clips: list[dict], steps: int, seed: int, lr: float, n_seg: int, seg_len: int, context: int = 5, log=print):
    import torch

    torch.manual_seed(seed)
    rng = np.random.default_rng([seed, 2])
    net = L.build_net(context=context)
    # auxiliary head (not exported): the audio embedding predicts the 5 frames' mouth features it is in sync with
    head = torch.nn.Linear(net.aud[-1].out_features, L.N_FEAT * 5)
    opt = torch.optim.AdamW(list(net.parameters()) + list(head.parameters()), lr=lr, weight_decay=1e-4)
    hist = []
    for step in range(steps):
        for pg in opt.param_groups:
            pg["lr"] = lr * min(1.0, (step + 1) / 100) * 0.5 * (1 + np.cos(np.pi * step / steps))
        v, a, shift, tgt = batch(clips, rng, n_seg, seg_len, context)
        a_emb, v_emb = net(torch.as_tensor(a), torch.as_tensor(v))
        w_con = 0.5 * min(1.0, max(0.0, (step - 0.3 * steps) / (0.2 * steps)))
        loss, parts = loss_fn(a_emb, v_emb, shift, w_con)
        aux = torch.nn.functional.mse_loss(head(a_emb), torch.as_tensor(tgt).flatten(1))
        loss = loss + max(0.0, 1.0 - step / (0.6 * steps)) * aux
        parts["aux"] = float(aux.detach())
        opt.zero_grad()
        loss.backward()
        opt.step()
        hist.append(parts)
        if (step + 1) % 200 == 0:
            m = {k: round(float(np.mean([h[k] for h in hist[-200:]])), 3) for k in parts}
            log(f"step {step + 1}/{steps}: {m}")
    return net.eval(), {k: float(np.mean([h[k] for h in hist[-200:]])) for k in hist[-1]}


# ----------------------------------------------------------------------------- acceptance
def render_heldout(specs: list[dict], folder: Path) -> list[dict]:
    """Held-out clips rendered in full, with dlib landmarks of their frames (cached)."""
    from lmgs_eval.data.bundled import synthesize_clip
    from lmgs_eval.metrics.landmarks import DlibBackend

    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for s in specs:
        p = folder / f"{s['id']}-{hashlib.sha256(json.dumps(s, sort_keys=True).encode()).hexdigest()[:12]}.npz"
        if not p.is_file():
            c = synthesize_clip(s["face"], s["text"], s["voice"], size=s["size"], seed=s["seed"])
            lms = DlibBackend(redetect=10).landmarks(c.frames)  # uint8, read as it is
            np.savez(p, lms=lms, gt_lms=c.lms2d, audio=c.audio)
        with np.load(p) as z:
            out.append({**s, "lms": z["lms"], "audio": z["audio"]})
    return out


def acceptance(scorer, held: list[dict], shifts=SHIFTS, log=print) -> dict:
    """Offsets, injected shifts and other-audio LSE-C of landmark clips through ``scoring.lse``."""
    rows = []
    for j, d in enumerate(held):
        other = held[(j + 1) % len(held)]["audio"]
        wrong = np.zeros_like(d["audio"])
        n = min(len(wrong), len(other))
        wrong[:n] = other[:n]
        gt = scoring.lse(None, d["audio"], scorer=scorer, lms=d["lms"], reference=True)
        wr = scoring.lse(None, wrong, scorer=scorer, lms=d["lms"])
        sh = {}
        for k in shifts:
            x, a = shifted(d["lms"], d["audio"], k)
            sh[str(k)] = scoring.lse(None, a, scorer=scorer, lms=x).values["offset"]
        row = {"id": d.get("id"), "offset": gt.values["offset"], "lse_c": gt.values["lse_c"], "lse_d": gt.values["lse_d"],
               "separation": gt.values["separation"], "trusted": gt.values["trusted"],
               "wrong_lse_c": wr.values["lse_c"], "wrong_trusted": wr.values["trusted"], "shift_offsets": sh}
        rows.append(row)
        log(json.dumps(row))
    hits = sum(r["shift_offsets"][str(k)] == -k for r in rows for k in shifts)
    return {"clips": len(rows), "synced_offset0": sum(r["offset"] == 0 for r in rows),
            "shift_exact": hits, "shift_trials": len(rows) * len(shifts), "shifts": list(shifts),
            "gt_lse_c_mean": float(np.mean([r["lse_c"] for r in rows])),
            "wrong_audio_lse_c_mean": float(np.mean([r["wrong_lse_c"] for r in rows])),
            "gt_above_wrong": sum(r["lse_c"] > r["wrong_lse_c"] for r in rows),
            "gt_trusted": sum(bool(r["trusted"]) for r in rows),
            "wrong_audio_trusted": sum(bool(r["wrong_trusted"]) for r in rows), "per_clip": rows}


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lmgs_eval.metrics.sync.train.landmark", description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="folder for landmark_sync.onnx + landmark_sync.json")
    ap.add_argument("--clips", type=int, default=320)
    ap.add_argument("--steps", type=int, default=3500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--segments", type=int, default=8)
    ap.add_argument("--seg-len", type=int, default=16)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--context", type=int, default=15, help="frames per video window (odd, >= 5; centred as syncnet_python's 5)")
    ap.add_argument("--highpass", type=int, default=0,
                    help="frames of the moving average removed from the mouth features (0: the clip mean only)")
    ap.add_argument("--heldout", type=int, default=10, help="held-out acceptance clips (rendered, dlib landmarks)")
    args = ap.parse_args(argv)

    import torch
    from tqdm import tqdm

    from lmgs_eval.paths import cache_root

    t0 = time.time()
    torch.set_num_threads(args.threads)
    sp = split()
    specs = clip_specs(args.clips, args.seed, sp)
    root = cache_root() / "sync_landmark_train"
    paths = build_corpus(specs, root / _cache_key(specs[:0] + [{"seed": args.seed}]), args.workers)
    clips = [c for c in (load_clip(p, args.seed, args.highpass) for p in tqdm(paths, desc="features", unit="clip")) if c is not None]
    t_corpus = time.time() - t0
    if args.context < 5 or args.context % 2 == 0:
        ap.error(f"--context {args.context}: must be odd and at least 5")
    net, final = train(clips, args.steps, args.seed, args.lr, args.segments, args.seg_len, args.context, log=tqdm.write)
    t_train = time.time() - t0 - t_corpus
    recipe = {
        "version": RECIPE_VERSION, "script": "python -m lmgs_eval.metrics.sync.train.landmark", "doc": "see the script's docstring",
        "faces": list(FACES), "sizes": list(SIZES), "voices": sp["train_voices"], "clips": len(clips),
        "windows": int(sum(c["last"] for c in clips)), "variants_per_clip": N_VARIANTS, "steps": args.steps,
        "context": args.context, "highpass": args.highpass,
        "lr": args.lr, "batch": {"segments": args.segments, "seg_len": args.seg_len}, "threads": args.threads,
        "final_train": final, "corpus_seconds": round(t_corpus, 1), "train_seconds": round(t_train, 1),
    }
    m = L.export(net, args.out, {"recipe": recipe, "seed": args.seed, "context": args.context, "highpass": args.highpass})
    if args.heldout:
        held = render_heldout(heldout_specs(args.heldout, sp), root / "heldout")
        scorer, _ = scorers.load_landmark(args.out)
        m["acceptance"] = acceptance(scorer, held, log=tqdm.write)
        from lmgs.fileio import atomic_write

        atomic_write(args.out / L.JSON_NAME, json.dumps(m, indent=2))
        print(json.dumps({k: v for k, v in m["acceptance"].items() if k != "per_clip"}, indent=2))
    print(f"wrote {args.out / L.ONNX_NAME} sha256 {m['sha256']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
