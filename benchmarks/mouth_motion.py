"""Does a trained method's mouth move? Its inner lips against the truth's, on training and test frames.

LMD says how far the rendered mouth lies from the truth's; it does not say whether the mouth
moves. A model that renders one neutral, half-open mouth scores a moderate LMD on every clip and
follows none of the speech. This renders a method (trained as ``lmgs-eval self`` trains it, or
loaded from the model cache when it already was) on two blocks of its own training frames and on
the test frames, and gives for each block PSNR (the toolkit's: a model that reproduces its training
frames far better than its test frames has learnt them, not the person), LMD and the inner lips'
opening (dlib's points 62 and 66, in pixels) of the render and of the truth: their mean and spread
over the frames, and the correlation of the two over time. A mouth that moves with the truth has a
spread near the truth's and a correlation near 1; one fitted as a still average has a small spread
on training frames too.
For lmgs it also gives the share of face points Spatial Enhancement selected on each block (the
paper reports about 20 %).

    python benchmarks/mouth_motion.py --subject anchor_de_20s --method lmgs [--set KEY=VALUE ...] [--seed N]

Training takes as long as ``lmgs-eval self`` (the model is cached under the same name, so a model
trained by ``self`` is only loaded); the scoring is dlib on about 140 frames.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def motion_row(name: str, rendered: np.ndarray, truth: np.ndarray) -> dict:
    """PSNR, LMD and the inner-lip opening of ``rendered`` against ``truth`` (both ``[T, H, W, 3]`` uint8)."""
    from lmgs.lips import lip_gap
    from lmgs_eval.metrics.image import PSNR
    from lmgs_eval.metrics.landmarks import create_backend, lmd_per_frame

    backend = create_backend("dlib")
    lp, lt = backend.landmarks(rendered), backend.landmarks(truth)
    ok = np.isfinite(lp).all(axis=(1, 2)) & np.isfinite(lt).all(axis=(1, 2))
    gp, gt = lip_gap(lp[ok]), lip_gap(lt[ok])  # points 62 and 66, in pixels
    r = float(np.corrcoef(gp, gt)[0, 1]) if ok.sum() > 2 and gp.std() > 0 and gt.std() > 0 else float("nan")
    scorer = PSNR()  # as the metric suite scores a run: uint8 chunks, each made float where it is computed
    return {"frames": name, "n": int(ok.sum()), "psnr": scorer.compute(scorer.stream()(rendered, truth)).value,
            "lmd": float(np.mean(lmd_per_frame(lp[ok], lt[ok]))),
            "opening_render": [float(gp.mean()), float(gp.std())], "opening_truth": [float(gt.mean()), float(gt.std())],
            "opening_r": r}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--subject", required=True)
    p.add_argument("--data-root", default=None, help="where the subject is (default: $LMGS_DATA or ~/.cache/lmgs/data)")
    p.add_argument("--method", default="lmgs")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config change, as `lmgs-eval self --set`")
    p.add_argument("--frames", type=int, default=46, help="frames in each block of training frames (default 46)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)

    from lmgs_eval.commands._common import parse_overrides
    from lmgs_eval.convert import driving_from_clip, subject_to_clip
    from lmgs_eval.data.registry import find_subject
    from lmgs_eval.errors import UserError
    from lmgs_eval.results.records import RunId
    from lmgs_eval.runner import RunConfig, build_method, takes_timings

    try:
        subject = find_subject(args.subject, args.data_root, progress=False)
        cfg = RunConfig(subject=args.subject, data_root=args.data_root, progress=False,
                        method_options=parse_overrides(args.overrides))
        method = build_method(cfg, args.method, subject)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    run = RunId(subject, method.describe(), args.seed)
    t0 = time.perf_counter()
    method.fit(subject_to_clip(subject, subject.train_ids, progress=False), seed=args.seed, workdir=run.model_dir,
               progress=False)
    fit_s = time.perf_counter() - t0
    train = list(subject.train_ids)
    k = args.frames
    blocks = (("training frames, the middle", train[len(train) // 2 - k // 2:][:k]),
              ("training frames, the last", train[-k:]), ("test frames", list(subject.test_ids)))
    rows = []
    for name, ids in blocks:
        clip = subject_to_clip(subject, ids, progress=False)
        truth = np.asarray(clip.frames)
        if truth.dtype != np.uint8:
            truth = np.clip(np.rint(truth * 255), 0, 255).astype(np.uint8)
        timings: dict = {}  # lmgs fills in the share of face points Spatial Enhancement selected
        kw = {"timings": timings} if takes_timings(method) else {}
        rows.append(motion_row(name, method.render(driving_from_clip(clip), **kw), truth))
        rows[-1]["se_share"] = timings.get("se_fraction")
    info = method.describe()
    out = {"subject": args.subject, "method": info.display_name, "config_hash": info.config_hash,
           "seed": args.seed, "fit_or_load_s": round(fit_s, 1), "rows": rows}
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"{out['method']} ({out['config_hash']}, seed {args.seed}) on {args.subject}; inner-lip opening in px")
    print(f"{'frames':30s} {'n':>3s} {'PSNR':>6s} {'LMD':>6s} {'render':>12s} {'truth':>12s} {'r':>6s} {'SE':>6s}")
    for r in rows:
        se = "" if r["se_share"] is None else f"{100 * r['se_share']:5.1f}%"
        print(f"{r['frames']:30s} {r['n']:3d} {r['psnr']:6.2f} {r['lmd']:6.2f} {r['opening_render'][0]:6.2f}+-{r['opening_render'][1]:<4.2f} "
              f"{r['opening_truth'][0]:6.2f}+-{r['opening_truth'][1]:<4.2f} {r['opening_r']:6.2f} {se:>6s}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
