"""Train the bundled SyncNet-style scorer (``weights/bundled_sync.{onnx,json}``).

``python -m lmgs_eval.metrics.sync.train.pixel --out lmgs_eval/metrics/sync/weights [--minutes M] [--seed S]``

Recipe (deterministic for a seed; recorded in ``bundled_sync.json``):

* **Corpus.** Clips rendered by the bundled generator (``synthesize_clip``) for both faces,
  frame sizes drawn from :data:`SIZES`, spoken by every available voice *except* the
  cross-driven voices of the bundled subjects (``generator.CROSS``, which include the
  subjects' own piper voice), saying two sentences each from the ``[train]`` sections of
  ``data/bundled/corpus.txt`` and ``metrics/sync/train/corpus.txt``. The cross-driven texts
  (``[cross-a]``, ``[cross-b]``) and ``corpus.txt [heldout]`` are never trained on;
  they make the held-out acceptance clips, with the held-out voices.
* **Crops.** Exactly the ``lse()`` pipeline: ``crops.face_boxes`` (dlib, every frame,
  median-9), ``crops.crop_faces`` (224 x 224 BGR), then ``SyncScorer.prepare`` (region
  ``mouth`` = ``pixel.MOUTH_BOX``, INTER_AREA to 48 x 48, 0..1; the ``lower_half`` region
  starts at the mouth of a dlib-box crop and often cuts it off). A second crop per clip comes from boxes jittered
  by a per-clip shift (+-6 % of the box) and scale (+-8 %).
* **Audio.** ``maths.mfcc_13`` of the clean audio and of two augmented copies (gain 0.25-2,
  white noise at 12-40 dB SNR, clipped to [-1, 1]); windows exactly as ``maths.windows``.
* **Cache.** One ``.npz`` per clip (frames, audio, boxes, MFCCs, articulation) under
  ``cache_root()/sync_train/<key>/`` (the key hashes the recipe) plus the prepared scorer
  inputs beside it, so reruns skip rendering. Training steps are ``--minutes`` x
  ``STEPS_PER_MINUTE`` (or ``--steps``), never a clock, so a seed gives one network.
* **Training.** Batches of contiguous 5-frame video windows from a few clips. Every video
  window is compared with every audio window of the batch: its own clip at offsets
  -15..15 and all other clips' windows. Loss = a SyncNet contrastive loss on the L2
  distance (positives: in sync; negatives: shifts of 3..15 frames and audio of other clips)
  plus a multi-way cross-entropy over ``-distance`` that also separates shifts of 1-2
  frames, so the minimum of the mean distance falls exactly on the true offset. From
  scratch this sits at chance for ~500 steps, so for the first 60 % of training both
  embeddings also regress the generator's ground-truth mouth articulation (jaw, lip width,
  rounding, closure, lip-to-teeth) of their 5 frames through linear heads that are not
  exported (weight decaying linearly to 0).
  Train-time augmentation: brightness/contrast per window, +-2 px translation, choice of
  crop and MFCC copy.
* **Acceptance** (held-out clips through the public ``lse()``): offset 0 on synced video,
  exact recovery of injected shifts, LSE-C of ground truth vs the same video with another
  clip's audio. The figures go into the JSON next to the sha256 of the ONNX.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from lmgs_eval.metrics.sync import maths, nets, pixel, scoring
from lmgs_eval.metrics.sync.probe import shifted
from lmgs_eval.metrics.sync.train.pixel_data import (FACES, HW, N_ART, RECIPE_VERSION, REGION, SIZES, build_cache, cache_dir,
                                               clip_specs, heldout_specs, load_clip, split)

SHIFTS = (-10, -5, -3, 3, 5, 10)
NEG_MIN_SHIFT = 3
STEPS_PER_MINUTE = 400  # measured on 2 cores of the development machine (see design.md)


# ----------------------------------------------------------------------------- training
def _batch(clips: list[dict], rng: np.random.Generator, n_seg: int, seg_len: int, vshift: int = maths.VSHIFT):
    """Segments of consecutive video windows and the audio windows around them.

    Returns video ``[B, 3, 5, H, W]`` (uint8 as float), audio ``[A, 1, 13, 20]``, and for each video
    window its positive column, its clip, and the shift of each audio column relative to it.
    """
    picks = rng.choice(len(clips), size=min(n_seg, len(clips)), replace=False)
    vids, auds, v_clip, v_pos, a_clip, a_idx, v_art, a_art = [], [], [], [], [], [], [], []
    for s, c in enumerate(picks):
        d = clips[c]
        last = d["last"]
        L = min(seg_len, last)
        i0 = int(rng.integers(0, last - L + 1))
        var = int(rng.integers(d["video"].shape[0]))
        mvar = int(rng.integers(d["awin"].shape[0]))
        v = d["video"][var]
        for i in range(i0, i0 + L):
            vids.append(v[i:i + 5])
            v_art.append(d["art"][i:i + 5].ravel())
            v_clip.append(s)
            v_pos.append(i)
        lo, hi = max(0, i0 - vshift), min(last, i0 + L + vshift)
        for j in range(lo, hi):
            auds.append(d["awin"][mvar, j])
            a_art.append(d["art"][j:j + 5].ravel())
            a_clip.append(s)
            a_idx.append(j)
    v = np.stack(vids).astype(np.float32) / 255.0  # [B, 5, H, W, 3]
    v = np.ascontiguousarray(v.transpose(0, 4, 1, 2, 3))
    a = np.stack(auds)[:, None]
    v_clip, v_pos, a_clip, a_idx = map(np.asarray, (v_clip, v_pos, a_clip, a_idx))
    same = v_clip[:, None] == a_clip[None, :]
    shift = np.where(same, a_idx[None, :] - v_pos[:, None], 10**6)
    return v, a, shift, np.stack(v_art), np.stack(a_art)


def _augment_video(v, g):
    import torch

    b = v.shape[0]
    contrast = 1.0 + (torch.rand(b, 1, 1, 1, 1, generator=g) - 0.5) * 0.5
    bright = (torch.rand(b, 1, 1, 1, 1, generator=g) - 0.5) * 0.3
    mean = v.mean(dim=(1, 2, 3, 4), keepdim=True)
    v = ((v - mean) * contrast + mean + bright).clamp(0, 1)
    dy, dx = [int(x) for x in torch.randint(-2, 3, (2,), generator=g)]
    if dy or dx:
        v = torch.roll(v, shifts=(dy, dx), dims=(3, 4))
    return v


def _loss(a_emb, v_emb, shift, margin: float, scale: float, w_con: float = 1.0):
    import torch

    d = torch.cdist(v_emb, a_emb) + 1e-6  # [B, A]
    sh = torch.as_tensor(shift)
    pos = sh == 0
    valid = (sh.abs() <= maths.VSHIFT) | (sh == 10**6)
    neg = valid & ((sh.abs() >= NEG_MIN_SHIFT))
    l_pos = (d[pos] ** 2).mean()
    l_neg = (torch.relu(margin - d[neg]) ** 2).mean()
    logits = (-scale * d).masked_fill(~valid, -1e9)
    target = pos.float().argmax(dim=1)
    l_ce = torch.nn.functional.cross_entropy(logits, target)
    with torch.no_grad():
        acc = (logits.argmax(dim=1) == target).float().mean()
    return w_con * (l_pos + l_neg) + l_ce, {"pos": float(l_pos.detach()), "neg": float(l_neg.detach()), "ce": float(l_ce.detach()), "acc": float(acc)}


def embed_audio(net, a):
    """``BundledSyncNet``'s audio branch alone (its ``forward`` runs both)."""
    return net.aud_fc(net.aud(a).mean(dim=(2, 3)))


def embed_video(net, v):
    return net.lip_fc(net.lip(net.lip3d(v)[:, :, 0]).mean(dim=(2, 3)))


def _embed_torch(net, a, v, bs=256):
    import torch

    with torch.no_grad():
        ae = torch.cat([embed_audio(net, torch.as_tensor(a[s:s + bs])) for s in range(0, len(a), bs)])
        ve = torch.cat([embed_video(net, torch.as_tensor(v[s:s + bs])) for s in range(0, len(v), bs)])
    return ae.numpy(), ve.numpy()


def quick_eval(net, clips: list[dict]) -> dict:
    """Torch-side check on cached held-out clips: offsets of synced and shifted windows."""
    import torch

    net.eval()
    hits, zero, n = 0, 0, 0
    conf = []
    with torch.no_grad():
        for d in clips:
            last = d["last"]
            v = np.stack([d["video"][0][i:i + 5] for i in range(last)]).astype(np.float32) / 255.0
            v = np.ascontiguousarray(v.transpose(0, 4, 1, 2, 3))
            ae, ve = _embed_torch(net, d["awin"][0][:, None], v)
            r = maths.lse_from_embeddings(ve, ae)
            zero += r["offset"] == 0
            conf.append(r["lse_c"])
            for k in SHIFTS:  # audio delayed by k frames -> offset -k
                if k > 0:
                    rr = maths.lse_from_embeddings(ve[k:], ae[:last - k])
                else:
                    rr = maths.lse_from_embeddings(ve[:last + k], ae[-k:])
                hits += rr["offset"] == -k
                n += 1
    net.train()
    return {"zero": int(zero), "clips": len(clips), "shift_hits": int(hits), "shift_n": n, "lse_c": float(np.mean(conf))}


# ----------------------------------------------------------------------------- acceptance
def acceptance(scorer, held: list[dict], log=print) -> dict:
    """Held-out clips through the public ``lse()``: synced, injected shifts, wrong audio."""
    rows = []
    for j, d in enumerate(held):
        fr = d["frames"]  # uint8, as the scorers read them
        au = d["audio"]
        gt = scoring.lse(fr, au, scorer=scorer)
        other = held[(j + 1) % len(held)]["audio"]
        n = min(len(au), len(other))
        wrong_audio = np.zeros_like(au)
        wrong_audio[:n] = other[:n]
        wr = scoring.lse(fr, wrong_audio, scorer=scorer)
        sh = {}
        for k in SHIFTS:
            f2, a2 = shifted(fr, au, k)
            sh[k] = scoring.lse(f2, a2, scorer=scorer).values["offset"]
        row = {"id": d["id"], "face": d["face"], "voice": d["voice"], "size": d["size"], "offset": gt.values["offset"],
               "lse_c": gt.values["lse_c"], "lse_d": gt.values["lse_d"], "wrong_lse_c": wr.values["lse_c"],
               "wrong_lse_d": wr.values["lse_d"], "shift_offsets": {str(k): v for k, v in sh.items()}}
        rows.append(row)
        log(json.dumps(row))
    n_shift = len(rows) * len(SHIFTS)
    hits = sum(r["shift_offsets"][str(k)] == -k for r in rows for k in SHIFTS)
    return {
        "clips": len(rows),
        "synced_offset0": sum(r["offset"] == 0 for r in rows),
        "shift_exact": hits, "shift_trials": n_shift, "shift_exact_rate": hits / max(1, n_shift),
        "shifts": list(SHIFTS),
        "gt_lse_c_mean": float(np.mean([r["lse_c"] for r in rows])),
        "wrong_audio_lse_c_mean": float(np.mean([r["wrong_lse_c"] for r in rows])),
        "gt_lse_d_mean": float(np.mean([r["lse_d"] for r in rows])),
        "wrong_audio_lse_d_mean": float(np.mean([r["wrong_lse_d"] for r in rows])),
        "gt_above_wrong": sum(r["lse_c"] > r["wrong_lse_c"] for r in rows),
        "per_clip": rows,
    }


def load_scorer(folder: Path):
    """The bundled scorer from ``folder`` exactly as ``find_scorer()`` loads it."""
    from lmgs.fileio import sha256_file
    from lmgs_eval.metrics.ort import load_session

    p, j = Path(folder) / "bundled_sync.onnx", Path(folder) / "bundled_sync.json"
    m = json.loads(j.read_text())
    return pixel.SyncScorer("bundled-sync", load_session(p), sha256_file(p), tuple(m["input_hw"]), m["region"], m["pixel"],
                           standin="bundled-sync")


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lmgs_eval.metrics.sync.train.pixel", description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="folder for bundled_sync.onnx + bundled_sync.json")
    ap.add_argument("--minutes", type=float, default=11.0, help="training wall time (after the corpus is cached)")
    ap.add_argument("--steps", type=int, default=0, help="optimizer steps (default: --minutes x %d)" % STEPS_PER_MINUTE)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--clips", type=int, default=140, help="training clips (two sentences each)")
    ap.add_argument("--heldout", type=int, default=10, help="held-out acceptance clips")
    ap.add_argument("--workers", type=int, default=2, help="processes rendering the corpus (not training)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads for training")
    ap.add_argument("--segments", type=int, default=6, help="clips per batch")
    ap.add_argument("--seg-len", type=int, default=12, help="consecutive windows per clip in a batch")
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--aux", type=float, default=1.0, help="weight of the articulation auxiliary loss (decays to 0 at 60%%)")
    ap.add_argument("--con", type=float, default=0.5, help="weight of the contrastive loss once ramped in")
    ap.add_argument("--con-start", type=float, default=0.4, help="fraction of the steps where the contrastive term starts")
    ap.add_argument("--no-accept", action="store_true", help="skip the held-out acceptance through lse()")
    args = ap.parse_args(argv)

    import torch
    from tqdm import tqdm

    t_start = time.time()
    sp = split()
    specs = clip_specs(args.clips, args.seed, sp)
    hspecs = heldout_specs(args.heldout, sp)
    meta = {"sizes": SIZES, "faces": FACES}
    folder = cache_dir(meta)
    paths = build_cache(specs, folder / "train", args.workers, "corpus")
    hpaths = build_cache(hspecs, folder / "heldout", args.workers, "held-out")
    t_corpus = time.time() - t_start
    clips = [load_clip(p) for p in tqdm(paths, desc="crops", unit="clip")]
    clips = [c for c in clips if c["last"] >= 8]
    held = [load_clip(p, keep_frames=True) for p in hpaths]
    for h, s in zip(held, hspecs):
        h.update({k: s[k] for k in ("id", "face", "voice", "size")})
    n_windows = int(sum(c["last"] for c in clips))

    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(args.seed)
    rng = np.random.default_rng([args.seed, 2])
    _, Bundled = nets.nets()
    net = Bundled()
    from torch import nn

    head_v, head_a = nn.Linear(net.lip_fc.out_features, 5 * N_ART), nn.Linear(net.aud_fc.out_features, 5 * N_ART)
    all_art = np.concatenate([c["art"] for c in clips])
    art_mu = torch.as_tensor(np.tile(all_art.mean(0), 5), dtype=torch.float32)
    art_sd = torch.as_tensor(np.tile(all_art.std(0) + 1e-3, 5), dtype=torch.float32)
    params = list(net.parameters()) + list(head_v.parameters()) + list(head_a.parameters())
    opt = torch.optim.AdamW(params, lr=args.lr, weight_decay=1e-4)
    margin, scale = 2.0, 4.0
    t0 = time.time()
    step, hist = 0, []
    # deterministic for a seed: the step count is a function of --minutes (or --steps), never of the clock
    n_steps = int(args.steps or max(40, round(args.minutes * STEPS_PER_MINUTE)))
    bar = tqdm(total=n_steps, desc="train", unit="step")
    while step < n_steps:
        total = n_steps
        lr = args.lr * min(1.0, (step + 1) / 100) * 0.5 * (1 + np.cos(np.pi * step / total))
        for pg in opt.param_groups:
            pg["lr"] = lr
        v, a, shift, v_art, a_art = _batch(clips, rng, args.segments, args.seg_len)
        vt = _augment_video(torch.as_tensor(v), g)
        a_emb = embed_audio(net, torch.as_tensor(a))
        v_emb = embed_video(net, vt)
        # the contrastive term alone collapses the embeddings to the |a - v| = margin / 2 equilibrium from
        # scratch, so it joins once the cross-entropy and the auxiliary heads have made them informative
        w_con = args.con * min(1.0, max(0.0, (step - args.con_start * n_steps) / (0.2 * n_steps)))
        loss, parts = _loss(a_emb, v_emb, shift, margin, scale, w_con)
        # auxiliary supervision (training only, heads not exported): both embeddings predict the
        # generator's ground-truth mouth articulation of their 5 frames, so they carry mouth shape early
        w_aux = args.aux * max(0.0, 1.0 - step / (0.6 * n_steps))
        l_aux = (nn.functional.mse_loss(head_v(v_emb), (torch.as_tensor(v_art) - art_mu) / art_sd)
                 + nn.functional.mse_loss(head_a(a_emb), (torch.as_tensor(a_art) - art_mu) / art_sd))
        loss = loss + w_aux * l_aux
        parts["aux"] = float(l_aux.detach())
        opt.zero_grad()
        loss.backward()
        opt.step()
        hist.append(parts)
        step += 1
        bar.update(1)
        if step % 25 == 0:
            m = {k: np.mean([h[k] for h in hist[-25:]]) for k in parts}
            bar.set_postfix_str(f"ce {m['ce']:.3f} acc {m['acc']:.2f} pos {m['pos']:.3f} neg {m['neg']:.3f} aux {m['aux']:.3f}")
        if step % 400 == 0:
            tqdm.write(f"step {step}: held-out (torch) {quick_eval(net, held)}")
    bar.close()
    t_train = time.time() - t0
    net.eval()
    q = quick_eval(net, held)
    print(f"final held-out (torch): {q}", flush=True)

    recipe = {
        "version": RECIPE_VERSION,
        "corpus": ("bundled generator synthesize_clip; two sentences per clip from data/bundled/corpus.txt [train] + "
                   "metrics/sync/train/corpus.txt [train]; cross-driven texts/voices and its [heldout] held out"),
        "faces": list(FACES), "sizes": list(SIZES), "voices": sp["train_voices"], "heldout_voices": sp["heldout_voices"],
        "texts": len(sp["train_texts"]), "heldout_texts": len(sp["heldout_texts"]), "clips": len(clips),
        "windows": n_windows,
        "crops": f"lse() pipeline: face_boxes (dlib every frame, median-9) + crop_faces 224 + SyncScorer.prepare "
                 f"(region {REGION}, INTER_AREA {HW[0]}x{HW[1]}, BGR 0..1)",
        "augmentations": ["second crop per clip from boxes jittered by +-6% shift and +-8% scale",
                          "two extra MFCC copies per clip: gain 0.25-2, white noise 12-40 dB SNR",
                          "brightness +-0.15, contrast x0.75-1.25 per window", "+-2 px translation per batch"],
        "objective": (f"contrastive (margin {margin}, weight 0 until {args.con_start:.0%} of the steps, then ramped to "
                      f"{args.con} over 20%) on L2 distance, positives in sync, negatives shifts "
                      f"{NEG_MIN_SHIFT}..15 frames and other clips' audio; plus cross-entropy over -{scale}*distance "
                      "against all shifts -15..15 and other clips"),
        "auxiliary": (f"ground-truth mouth articulation (jaw, lip width, rounding, closure, lip-to-teeth) of the 5 "
                      f"frames regressed from both embeddings by linear heads (not exported), weight {args.aux} "
                      "decaying linearly to 0 at 60% of the steps"),
        "batch": {"segments": args.segments, "seg_len": args.seg_len}, "optimizer": f"AdamW lr {args.lr} cosine, wd 1e-4",
        "steps": step, "train_seconds": round(t_train, 1), "corpus_seconds": round(t_corpus, 1),
        "threads": args.threads, "heldout_torch": q,
    }
    from lmgs.fileio import sha256_file
    from lmgs.fileio import atomic_write

    args.out.mkdir(parents=True, exist_ok=True)
    m = nets.export_bundled(net, args.out, {"recipe": recipe, "seed": args.seed, "input_hw": list(HW),
                                            "region": REGION, "pixel": "bgr_0_1"})
    if not args.no_accept:
        scorer = load_scorer(args.out)
        acc = acceptance(scorer, held, log=lambda s: tqdm.write(s))
        m["acceptance"] = acc
        m["recipe"]["total_seconds"] = round(time.time() - t_start, 1)
        assert sha256_file(args.out / "bundled_sync.onnx") == m["sha256"]
        atomic_write(args.out / "bundled_sync.json", json.dumps(m, indent=2))
        print(json.dumps({k: v for k, v in acc.items() if k != "per_clip"}, indent=2))
    print(f"wrote {args.out / 'bundled_sync.onnx'} sha256 {m['sha256']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
