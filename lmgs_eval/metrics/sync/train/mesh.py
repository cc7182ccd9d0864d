"""Train the mesh sync scorer (``weights/mesh_sync.{onnx,json}``) and measure it leave-one-speaker-out.

``python -m lmgs_eval.metrics.sync.train.mesh --footage DIR --out lmgs_eval/metrics/sync/weights``

The scorer (:mod:`~lmgs_eval.metrics.sync.mesh`) has the landmark scorer's network and windows; what
differs is where its mouth points come from (the dense face mesh in the canonical face frame) and what it
has seen. Recipe (deterministic for a seed and thread count; recorded in ``mesh_sync.json``):

* **Start**: the shipped landmark scorer's weights (``landmark_sync.onnx``, its sha256 checked), trained on
  the generator's clips (:mod:`~lmgs_eval.metrics.sync.train.landmark`).
* **Adapt** on real recordings with their own speech (the lip tracks of
  :mod:`lmgs_eval.data.ingest.lips`), every batch half real segments and half generated ones (the lip
  corpus's espeak-ng clips, :func:`lmgs_eval.data.lip_corpus.generated_recordings`), so the generated
  faces are not forgotten. Each real recording enters as the tracked mouth plus :data:`N_VARIANTS` ``- 1``
  draws of mild tracking noise, its audio clean plus copies with noise, a low-pass and a vocal-tract-length
  warp (the landmark recipe's audio augmentation). The mouth features lose their 1-second moving average
  (:data:`HIGHPASS` frames) rather than the clip mean: a real face's smiles and posture move the mouth more
  slowly than speech does. Objective: the landmark recipe's (cross-entropy over
  ``-4 x distance`` against the same clip's windows at shifts -15..15 and every window of the other clips
  in the batch, plus the margin term), from the start.
* **Leave one speaker out** (:func:`folds`): for each speaker of the footage a model adapted without any of
  that speaker's recordings scores that speaker's clips; only those figures are reported. The shipped
  weights are adapted on every recording (the same recipe), so the figures describe the recipe on a face
  it has not seen, which is what a user's footage is.

Per clip (:func:`evaluate`, through the public :func:`~lmgs_eval.metrics.sync.scoring.lse`): the offset of
the clip as it is (in sync), the offsets found with the audio delayed by -10, -5, +5 and +10 frames, the
clip's LSE-C against the LSE-C with every other speaker's audio in place of its own, and the self-check.
``lmgs-eval bench sync --footage DIR`` runs the folds and prints the table.
"""

from __future__ import annotations

import argparse
import json
import time
import zlib
from pathlib import Path

import numpy as np

from lmgs_eval.metrics.sync import landmark as L
from lmgs_eval.metrics.sync import maths, scoring
from lmgs_eval.metrics.sync.probe import shifted

RECIPE_VERSION = "1"
N_VARIANTS = 3
SHIFTS = (-10, -5, 5, 10)
ADAPT = {"steps": 300, "lr": 5e-4, "segments": 8, "seg_len": 16, "real_share": 0.5, "w_con": 0.5}
N_GENERATED = 160  # generated recordings in the adaptation mix
HIGHPASS = 25  # frames: the mouth features' moving average removed (expression and posture drift, not speech)


# ----------------------------------------------------------------------------- data
def _rng(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


def clip_inputs(name: str, lms68: np.ndarray, audio: np.ndarray, seed: int, variants: int = N_VARIANTS,
                highpass: int = HIGHPASS) -> dict | None:
    """A recording as training inputs: mouth features ``feat [V, T, 40]`` (the tracked mouth, then noisy draws)
    and normalised MFCCs ``mfcc [V, 13, M]`` (clean, then augmented), ``last`` windows; None when too short."""
    from lmgs_eval.metrics.sync.mesh import mouth_points
    from lmgs_eval.metrics.sync.train.landmark import noisy_audio, noisy_landmarks, warped_mfcc

    pts = mouth_points(lms68)
    last = min(len(pts), len(audio) // maths.SAMPLES_PER_FRAME) - 5
    if last < 8:
        return None
    rng = _rng(seed, name)
    pts, _ = L.fill_missing(pts)
    feats = [L.mouth_features(pts, highpass)]
    feats += [L.mouth_features(_mild(noisy_landmarks, pts, rng), highpass) for _ in range(variants - 1)]
    mf = [L.audio_features(maths.mfcc_13(audio))]
    mf += [L.audio_features(warped_mfcc(noisy_audio(audio, rng), rng.uniform(0.85, 1.18))) for _ in range(variants - 1)]
    m = min(x.shape[1] for x in mf)
    return {"name": name, "feat": np.stack(feats), "mfcc": np.stack([x[:, :m] for x in mf]), "last": last}


def _mild(noise, pts: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The landmark recipe's tracking noise at half strength (the mesh tracker jitters less than dlib)."""
    x = noise(pts, rng)
    return pts + 0.5 * (x - pts)


def generated_inputs(seed: int, n: int = N_GENERATED, highpass: int = HIGHPASS, progress=None) -> list[dict]:
    """:data:`N_GENERATED` generated recordings of the lip corpus (every ``k``-th), as :func:`clip_inputs`."""
    from lmgs_eval.data.lip_corpus import generated_recordings

    recs = generated_recordings()
    step = max(1, len(recs) // n)
    out = []
    for r in recs[::step][:n]:
        d = clip_inputs(r.name, r.lms68, r.audio, seed, highpass=highpass)
        if d is not None:
            out.append(d)
        if progress is not None:
            progress(len(out), n)
    return out


def real_inputs(recordings, seed: int, highpass: int = HIGHPASS) -> list[dict]:
    out = []
    for r in recordings:
        d = clip_inputs(r.name, r.lms68, r.audio, seed, highpass=highpass)
        if d is not None:
            d["speaker"] = r.speaker
            out.append(d)
    return out


# ----------------------------------------------------------------------------- training
def pretrained_net(context: int | None = None):
    """The shipped landmark scorer's network in torch (weights read from its ONNX graph, sha256 checked)."""
    import onnx
    import torch
    from onnx import numpy_helper

    from lmgs_eval.metrics.sync import scorers

    sc, why = scorers.load_landmark()
    if sc is None:
        raise RuntimeError(why)
    model = onnx.load(str(scorers.WEIGHTS / L.ONNX_NAME))
    sd = {i.name: torch.from_numpy(numpy_helper.to_array(i).copy()) for i in model.graph.initializer}
    net = L.build_net(context=sc.context if context is None else context)
    net.load_state_dict(sd)
    return net, sc


def adapt(net, real: list[dict], generated: list[dict], seed: int, steps: int = ADAPT["steps"], lr: float = ADAPT["lr"],
          segments: int = ADAPT["segments"], seg_len: int = ADAPT["seg_len"], real_share: float = ADAPT["real_share"],
          w_con: float = ADAPT["w_con"], context: int = 15, log=None):
    """``net`` (a copy) adapted on ``real`` with ``generated`` mixed into every batch; ``(net, final losses)``."""
    import copy

    import torch

    from lmgs_eval.metrics.sync.train.landmark import batch, loss_fn

    torch.manual_seed(seed)
    rng = np.random.default_rng([seed, 3])
    net = copy.deepcopy(net).train()
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    n_real = min(len(real), max(1, int(round(segments * real_share)))) if real else 0
    hist = []
    for step in range(steps):
        for pg in opt.param_groups:
            pg["lr"] = lr * min(1.0, (step + 1) / 50) * 0.5 * (1 + np.cos(np.pi * step / steps))
        pick = [real[i] for i in rng.choice(len(real), n_real, replace=False)] if n_real else []
        pick += [generated[i] for i in rng.choice(len(generated), segments - n_real, replace=False)]
        v, a, shift, _ = batch(pick, rng, len(pick), seg_len, context)
        a_emb, v_emb = net(torch.as_tensor(a), torch.as_tensor(v))
        loss, parts = loss_fn(a_emb, v_emb, shift, w_con)
        opt.zero_grad()
        loss.backward()
        opt.step()
        hist.append(parts)
        if log is not None and (step + 1) % 100 == 0:
            log(f"step {step + 1}/{steps}: " + json.dumps({k: round(float(np.mean([h[k] for h in hist[-100:]])), 3)
                                                           for k in parts}))
    return net.eval(), {k: float(np.mean([h[k] for h in hist[-100:]])) for k in hist[-1]}


class TorchSession:
    """An ONNX-Runtime-like ``run`` over a torch scorer network (scoring during training, before export)."""

    def __init__(self, net):
        self.net = net

    def run(self, names, feeds):
        import torch

        with torch.no_grad():
            a, v = self.net(torch.as_tensor(feeds["audio"]), torch.as_tensor(feeds["video"]))
        return [a.numpy(), v.numpy()]


# ----------------------------------------------------------------------------- evaluation
def evaluate(scorer, lms68: np.ndarray, audio: np.ndarray, others: list[np.ndarray], shifts=SHIFTS) -> dict:
    """The per-clip figures of the module doc for one in-sync recording (``lms68`` the canonical 68 points)."""
    own = scoring.lse(None, audio, scorer=scorer, lms=lms68, reference=True)
    v = own.values
    row = {"offset": v["offset"], "lse_c": v["lse_c"], "lse_d": v["lse_d"], "separation": v["separation"],
           "trusted": v["trusted"], "shifts": {}}
    for k in shifts:
        x, a = shifted(lms68, audio, k)
        row["shifts"][str(k)] = scoring.lse(None, a, scorer=scorer, lms=x).values["offset"]
    cs = [scoring.lse(None, np.resize(o, len(audio)), scorer=scorer, lms=lms68).values["lse_c"] for o in others]
    row["other_lse_c_max"] = float(max(cs)) if cs else None
    row["shifts_within_1"] = sum(abs(o + int(k)) <= 1 for k, o in row["shifts"].items())
    row["own_above_other"] = bool(cs) and v["lse_c"] > max(cs)
    row["passes"] = (abs(v["offset"]) <= 1 and row["shifts_within_1"] == len(shifts) and row["own_above_other"]
                     and bool(v["trusted"]))
    row["confident_wrong"] = bool(v["trusted"]) and not row["passes"]
    return row


def heldout_generated(n: int = 10) -> list[dict]:
    """The landmark scorer's held-out generated clips (held-out voices and texts, rendered in full), with the
    dense mesh tracked on their frames as on any user's footage; cached."""
    import hashlib

    from lmgs_eval.data.bundled import synthesize_clip
    from lmgs_eval.metrics.sync.crops import FaceClip
    from lmgs_eval.metrics.sync.train.landmark import heldout_specs, split
    from lmgs_eval.paths import cache_root

    folder = cache_root() / "sync_mesh_train" / "heldout"
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for s in heldout_specs(n, split()):
        p = folder / f"{s['id']}-{hashlib.sha256(json.dumps(s, sort_keys=True).encode()).hexdigest()[:12]}.npz"
        if not p.is_file():
            c = synthesize_clip(s["face"], s["text"], s["voice"], size=s["size"], seed=s["seed"])
            np.savez(p, lms=FaceClip(c.frames).mesh_landmarks(), audio=c.audio)
        with np.load(p) as z:
            out.append({**s, "lms": z["lms"], "audio": z["audio"]})
    return out


def generated_acceptance(scorer, held: list[dict], shifts=(-10, -5, -3, 3, 5, 10)) -> dict:
    """The landmark scorer's held-out acceptance for this scorer: offsets in sync, injected shifts exact, another
    clip's audio below the clip's own."""
    rows = []
    for j, d in enumerate(held):
        other = held[(j + 1) % len(held)]["audio"]
        r = evaluate(scorer, d["lms"], d["audio"], [other], shifts)
        rows.append({"id": d["id"], **{k: r[k] for k in ("offset", "lse_c", "other_lse_c_max", "separation", "trusted",
                                                         "shifts")}})
    return {"clips": len(rows), "synced_offset0": sum(r["offset"] == 0 for r in rows),
            "shift_exact": sum(o == -int(k) for r in rows for k, o in r["shifts"].items()),
            "shift_trials": len(rows) * len(shifts), "gt_above_wrong": sum(r["lse_c"] > r["other_lse_c_max"] for r in rows),
            "gt_trusted": sum(bool(r["trusted"]) for r in rows), "per_clip": rows}


def folds(recordings) -> list[str]:
    """The speakers of the footage, one fold each."""
    return sorted({r.speaker for r in recordings})


def fold_rows(recordings, speakers, seed: int = 0, generated: list[dict] | None = None, log=None, highpass: int = HIGHPASS,
              **adapt_kw) -> list[dict]:
    """The per-clip rows of the folds of ``speakers``: for each, a model adapted on every other speaker's recordings
    (:func:`adapt`) scores that speaker's clips (:func:`evaluate`); ``log`` gets one line a fold."""
    from lmgs_eval.metrics.sync.mesh import MeshScorer

    base, sc = pretrained_net()
    generated = generated if generated is not None else generated_inputs(seed, highpass=highpass)
    real = real_inputs(recordings, seed, highpass=highpass)
    rows = []
    for i, spk in enumerate(speakers):
        t0 = time.perf_counter()
        train = [d for d in real if d["speaker"] != spk]
        net, _ = adapt(base, train, generated, seed, context=sc.context, **adapt_kw)
        scorer = MeshScorer(TorchSession(net), "fold", sc.context, highpass)
        others = [o.audio for o in recordings if o.speaker != spk]
        mine = [{"clip": r.name, "speaker": spk, **evaluate(scorer, r.lms68, r.audio, others),
                 "trained_on": [d["name"] for d in train], "adapt_seconds": round(time.perf_counter() - t0, 1)}
                for r in recordings if r.speaker == spk]
        rows += mine
        if log is not None:
            log(f"fold {i + 1}/{len(speakers)}, speaker {spk} held out (adapted on {len(train)} real recordings): "
                + "; ".join(f"{m['clip']} offset {m['offset']:+d}, delays found {m['shifts_within_1']}/{len(SHIFTS)}, "
                            f"LSE-C {m['lse_c']:.2f} vs other speech {m['other_lse_c_max']:.2f}, trusted {m['trusted']}, "
                            f"{'pass' if m['passes'] else 'FAIL'}" for m in mine)
                + f" ({time.perf_counter() - t0:.0f} s)")
    return rows


def loso(recordings, seed: int = 0, generated: list[dict] | None = None, log=None, **kw) -> dict:
    """Leave one speaker out over every speaker of ``recordings``: :func:`summary` of :func:`fold_rows`."""
    return summary(fold_rows(recordings, folds(recordings), seed, generated, log, **kw))


def dlib_track(path: Path) -> np.ndarray:
    """dlib's 68 landmarks ``[T, 68, 2]`` of a video's 25 fps frames (the frames the mesh tracks read, tracked as
    the landmark scorer's input is), cached beside the lip tracks by the video's sha256."""
    from lmgs.fileio import sha256_file
    from lmgs_eval.data.ingest import decode
    from lmgs_eval.data.ingest.lips import cache_dir
    from lmgs_eval.metrics.landmarks import DlibBackend

    path = Path(path)
    f = cache_dir() / f"{path.stem}-{sha256_file(path)[:16]}-dlib-v1.npy"
    if f.is_file():
        return np.load(f)
    info = decode.probe(path)
    feed = DlibBackend(redetect=10).tracker()
    out = np.full((info.n_frames, 68, 2), np.nan)
    for k, img in decode.frames_25fps(info):
        out[k] = feed(img[None])[0]
    f.parent.mkdir(parents=True, exist_ok=True)
    tmp = f.with_suffix(".tmp.npy")
    np.save(tmp, out)
    tmp.replace(f)
    return out


def landmark_rows(recordings, footage: Path, log=None) -> list[dict]:
    """The same per-clip figures (:func:`evaluate`) for the shipped landmark scorer fed dlib's landmarks (trained
    on generated clips only: nothing to hold out)."""
    from lmgs_eval.metrics.sync import scorers

    sc, why = scorers.load_landmark()
    if sc is None:
        raise RuntimeError(why)
    rows = []
    for r in recordings:
        others = [o.audio for o in recordings if o.speaker != r.speaker]
        lms = dlib_track(Path(footage) / f"{r.name}.mp4")
        rows.append({"clip": r.name, "speaker": r.speaker, **evaluate(sc, lms, r.audio, others)})
        if log is not None:
            m = rows[-1]
            log(f"landmark scorer (dlib) on {r.name}: offset {m['offset']:+d}, delays found {m['shifts_within_1']}/"
                f"{len(SHIFTS)}, trusted {m['trusted']}, {'pass' if m['passes'] else 'FAIL'}")
    return rows


def summary(rows: list[dict]) -> dict:
    return {"clips": len(rows), "passes": sum(r["passes"] for r in rows),
            "offset_within_1": sum(abs(r["offset"]) <= 1 for r in rows),
            "all_shifts_within_1": sum(r["shifts_within_1"] == len(SHIFTS) for r in rows),
            "own_above_other": sum(r["own_above_other"] for r in rows), "trusted": sum(bool(r["trusted"]) for r in rows),
            "confident_wrong": sum(r["confident_wrong"] for r in rows), "per_clip": rows}


def meets_acceptance(loso_summary: dict, generated: dict | None) -> bool:
    """At least 9 clips in 11 pass, no clip fails with a trusted self-check, and on the held-out generated clips every
    offset is 0 and every injected shift exact."""
    ok = 11 * loso_summary["passes"] >= 9 * loso_summary["clips"] and loso_summary["confident_wrong"] == 0
    if generated is not None:
        ok = ok and generated["synced_offset0"] == generated["clips"] and generated["shift_exact"] == generated["shift_trials"]
    return bool(ok)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lmgs_eval.metrics.sync.train.mesh", description=__doc__.split("\n")[0])
    ap.add_argument("--footage", type=Path, required=True, help="folder of in-sync talking-head videos (*.mp4)")
    ap.add_argument("--out", type=Path, required=True, help="folder for mesh_sync.onnx + mesh_sync.json")
    ap.add_argument("--no-loso", action="store_true", help="skip the leave-one-speaker-out folds (the manifest then "
                    "records no figures on real footage, and auto does not use the scorer)")
    ap.add_argument("--heldout", type=int, default=10, help="held-out generated clips to check (0: none)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=ADAPT["steps"])
    ap.add_argument("--lr", type=float, default=ADAPT["lr"])
    ap.add_argument("--highpass", type=int, default=HIGHPASS)
    args = ap.parse_args(argv)

    import sys

    import torch

    from lmgs_eval.data.lip_corpus import real_recordings
    from lmgs_eval.metrics.sync.mesh import MeshScorer, export

    t0 = time.time()
    torch.set_num_threads(args.threads)
    log = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    recs = real_recordings(args.footage)
    gen = generated_inputs(args.seed, highpass=args.highpass)
    kw = {"steps": args.steps, "lr": args.lr}
    meta: dict = {}
    if not args.no_loso:
        res = loso(recs, args.seed, gen, log, highpass=args.highpass, **kw)
        meta["loso"] = {**{k: v for k, v in res.items() if k != "per_clip"},
                        "per_clip": [{k: v for k, v in r.items() if k != "trained_on"} for r in res["per_clip"]]}
    base, sc = pretrained_net()
    real = real_inputs(recs, args.seed, highpass=args.highpass)
    net, final = adapt(base, real, gen, args.seed, context=sc.context, **kw)
    if args.heldout:
        held = heldout_generated(args.heldout)
        meta["generated_acceptance"] = generated_acceptance(MeshScorer(TorchSession(net), "adapted", sc.context,
                                                                       args.highpass), held)
    if "loso" in meta:
        meta["loso"]["meets_acceptance"] = meets_acceptance(meta["loso"], meta.get("generated_acceptance"))
    recipe = {"version": RECIPE_VERSION, "script": "python -m lmgs_eval.metrics.sync.train.mesh",
              "doc": "see the script's docstring", "start": f"landmark_sync.onnx sha256 {sc.sha256}",
              "real": [{"clip": r.name, "speaker": r.speaker, "frames": int(len(r.lms68))} for r in recs],
              "generated": len(gen), "variants_per_clip": N_VARIANTS, **ADAPT, **kw, "highpass": args.highpass,
              "threads": args.threads, "final_train": final, "seconds": round(time.time() - t0, 1)}
    m = export(net, args.out, {"recipe": recipe, "seed": args.seed, "context": sc.context, "highpass": args.highpass,
                               **meta})
    print(json.dumps({k: ({kk: vv for kk, vv in v.items() if kk != "per_clip"} if isinstance(v, dict) else v)
                      for k, v in m.items() if k in ("loso", "generated_acceptance", "sha256")}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
