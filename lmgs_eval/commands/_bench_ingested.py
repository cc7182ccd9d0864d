"""``lmgs-eval bench ingested``: one method on a bundled subject, and on the ingest of its own raw video.

The bundled generator writes each subject's raw video (``<name>.mp4``, with audio) beside the
processing it made from its own knowledge (exact masks, poses, landmarks). Here that video
is ingested (``lmgs-eval ingest``, uncropped, at the subject's size) into a temporary data
root, and the method is trained on both folders as ``bench stripped`` does
(:mod:`lmgs_eval.commands._bench_pair`): each run is scored against its own folder's ground
truth, as ``lmgs-eval self`` would score it.

Besides the full-frame figures, ``PSNR away from the head outline`` leaves out the pixels
within ``--band`` pixels of either folder's head outline, in both runs. The outline decides
which pixels of a test frame its own torso layer supplies and which the method renders, and
the two folders draw it differently (the generator's head layer is narrower than the head it
shows); the figure says how much of the full-frame difference lives there
(``lmgs_eval/data/ingest/design.md``, "End to end").

Defaults: the bundled 60 s at 256 px, the ``quick`` preset (an ingest of about a minute and
two trainings of 4-10 minutes each on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

IN_ALL = False  # an ingest and two trainings, not a speed benchmark: `bench all` leaves it out
HELP = "a method trained on a bundled subject and on the ingest of its raw video, side by side"
BAND_PX = 4


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lmgs_eval.commands._bench_pair import add_arguments as pair_arguments

    pair_arguments(p)
    p.add_argument("--band", type=int, default=BAND_PX,
                   help=f"half width in pixels of the band around each head outline left out of the second PSNR (default {BAND_PX})")


def run(args: argparse.Namespace) -> dict:
    from lmgs_eval.commands import _bench_pair as pair
    from lmgs_eval.data.ingest import IngestConfig, ingest
    from lmgs_eval.data.ingest.compare import compare, edge_band, head_masks
    from lmgs_eval.data.registry import ensure_bundled
    from lmgs_eval.errors import UserError
    from lmgs_eval.metrics.image import psnr_outside

    if not 0 <= args.band <= 64:
        raise UserError(f"--band {args.band}: must be between 0 and 64 pixels")
    spec = pair.bundled_spec(args)
    t0 = time.perf_counter()
    truth_root = ensure_bundled(spec, args.data_root, progress=False)
    build_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory(prefix="lmgs-bench-ingested-") as tmp:
        tmp = Path(tmp)
        results = Path(args.results) if args.results else tmp / "results"
        t0 = time.perf_counter()
        ing_root = ingest(truth_root / f"{spec.name}.mp4", f"{spec.folder}-ingested", data_root=tmp / "data",
                          cfg=IngestConfig(size=spec.size, crop="none"), progress=False)
        ingest_s = time.perf_counter() - t0
        man = json.loads((ing_root / "manifest.json").read_text())
        runs = {"generator": pair.prepare(truth_root), "ingested": pair.prepare(ing_root)}
        gen, ing = runs["generator"], runs["ingested"]
        if man["frames"]["first_source_frame"] != 0 or gen["subject"].n_frames != ing["subject"].n_frames:
            raise UserError(f"{ing_root}: the ingest kept frames {man['frames']['first_source_frame']}.."
                            f"{man['frames']['first_source_frame'] + man['frames']['kept'] - 1} of {gen['subject'].n_frames}: "
                            "the two folders' frames do not line up")
        acc = compare(truth_root, ing_root)
        _, config_hash = pair.train_both(args, runs, tmp, results, "ingested")
        ids = gen["subject"].test_ids
        band = edge_band(head_masks(truth_root, ids), args.band) | edge_band(head_masks(ing_root, ids), args.band)
        away = {}
        for label, r in runs.items():
            frames = r["method"].render(r["driving"])  # the frames fit_render_score scored (rendering is deterministic)
            away[label] = psnr_outside(frames, r["test"].frames, band)
        rows = pair.rows(gen, ing, ("generator", "ingested"))
        rows.insert(1, {"figure": f"PSNR dB away from the head outlines (+-{args.band} px)", "generator": away["generator"],
                        "ingested": away["ingested"], "ingested - generator": away["ingested"] - away["generator"],
                        "note": f"{100 * band.mean():.1f} % of the test pixels left out"})
        rec = ing["record"]
        out = {
            "subject": f"{spec.folder} ({spec.size} px, {spec.seconds:g} s, bundled; built in {build_s:.1f} s)",
            "generator": str(truth_root),
            "ingested": f"{ing_root} (removed at the end; ingested in {ingest_s:.1f} s)",
            "ingest accuracy": (f"landmarks {acc['landmark_px']:.2f} px, rotation {acc['rotation_deg']:.2f} deg, "
                                f"head IoU {acc['head_iou']:.3f}, plate {acc['plate_psnr']:.1f} dB"),
            "method": f"{args.method} (preset {args.preset}, config {config_hash}, seed {args.seed}"
                      + (f", --set {' '.join(args.overrides)}" if args.overrides else "") + ")",
            "frames": f"{len(gen['train'])} train / {len(gen['test'])} test, {gen['subject'].width} px",
            "lpips": (rec["metrics"].get("lpips") or {}).get("backend"),
            "cores": os.cpu_count(),
            "load_avg_1min": round(os.getloadavg()[0], 2),
            "results": str(results) if args.results else "temporary (--results keeps the records)",
            "rows": rows,
        }
    return out
