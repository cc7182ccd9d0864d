"""``lmgs-eval bench ingest``: frames/s of every ingest stage, and its accuracy against the truth.

By default a bundled subject's own raw video (built on first use: 60 s at 512 px, the size the
ingest is budgeted for: at most 5 minutes on 2 cores) is ingested into a temporary data root;
``--video`` times any other video instead (no truth then). ``--hair head`` builds the subject
with all its hair moving with the head, ``--lossless`` ingests its frames and audio encoded
without loss, so that the accuracy is the ingest's alone. Wall and CPU seconds are both
reported: on a shared machine the wall time includes waiting for the cores.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import tempfile
import time
from pathlib import Path

HELP = "ingest speed per stage (frames/s) and accuracy against a bundled subject's truth"
BUDGET_S = 300.0  # a 60 s 512x512 clip on 2 cores


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--subject", default="astronaut", help="bundled subject whose raw video is ingested (default astronaut)")
    p.add_argument("--seconds", type=float, default=60.0, help="length of the bundled clip (default 60)")
    p.add_argument("--size", type=int, default=512, help="frame size of the bundled clip and of the ingest (default 512)")
    p.add_argument("--video", help="time this video instead (no ground truth)")
    p.add_argument("--hair", choices=("layer", "head"), default="layer",
                   help="layer: the bundled subject as built; head: a copy (built in a temporary folder) whose hair all "
                        "moves with the head and is labelled head")
    p.add_argument("--lossless", action="store_true",
                   help="ingest the subject's frames and audio encoded without loss instead of its H.264 video: the "
                        "accuracy is then the ingest's alone, without the codec's")
    p.add_argument("--motion", choices=("still", "turn", "zoom"), default="still",
                   help="the bundled subject's head motion: still (as built), turn (yaw +-28 deg, pitch +-10 deg) or zoom "
                        "(the camera's focal +-8 %%); the variants are built in a temporary folder")
    p.add_argument("--pose-from", choices=("mesh", "landmarks"), default=None,
                   help="the ingest's pose source (default: the ingest's own default)")
    p.add_argument("--pose-smooth", default=None, metavar="auto|FRAMES",
                   help="the ingest's pose smoothing: auto or a Gaussian's sigma in frames (default: the ingest's own)")
    p.add_argument("--priors", choices=("ellipsoid", "mesh"), default=None,
                   help="the ingest's depth / normal priors (default: the ingest's own default)")
    p.add_argument("--data-root", help="where bundled subjects are built (default: $LMGS_DATA or ~/.cache/lmgs/data)")
    p.add_argument("--jobs", type=int, default=None, help="processes for the per-frame stages (default: CPU count, at most 4)")


def _cpu() -> float:
    """CPU seconds of this process and of its finished worker processes."""
    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                  resource.getrusage(resource.RUSAGE_CHILDREN)))


def run(args: argparse.Namespace) -> dict:
    from lmgs_eval.data.ingest import IngestConfig, ingest
    from lmgs_eval.data.ingest.compare import bundled_truth, compare, lossless_video
    from lmgs_eval.data.bundled_spec import BundledSpec
    from lmgs_eval.errors import UserError

    if args.video and (args.hair != "layer" or args.lossless or args.motion != "still"):
        raise UserError("--video: times that video alone; --hair, --motion and --lossless apply to the bundled subject's")
    from lmgs_eval.data.ingest.pipeline import pose_sigma_from

    cfg = IngestConfig(size=args.size, **({"pose_from": args.pose_from} if args.pose_from else {}),
                       **({"priors": args.priors} if args.priors else {}),
                       **({"pose_sigma": pose_sigma_from(args.pose_smooth)} if args.pose_smooth is not None else {}))
    with tempfile.TemporaryDirectory(prefix="lmgs-bench-ingest-") as tmp:
        truth = None
        if args.video:
            video = Path(args.video)
        else:
            truth = bundled_truth(BundledSpec(args.subject, args.size, args.seconds), args.hair, Path(tmp), args.data_root,
                                  motion=None if args.motion == "still" else args.motion)
            video = truth / f"{args.subject}.mp4"
            if args.lossless:
                video = lossless_video(truth, Path(tmp) / "lossless" / video.name)
        t0, c0 = time.perf_counter(), _cpu()
        folder = ingest(video, "bench", data_root=tmp, cfg=cfg, progress=False, jobs=args.jobs)
        wall, cpu = time.perf_counter() - t0, _cpu() - c0
        man = json.loads((folder / "manifest.json").read_text())
        acc = compare(truth, folder) if truth is not None else {}
    n = man["frames"]["kept"]
    rows = [{"stage": k, "seconds": v["seconds"], "frames_per_s": v["frames_per_s"]} for k, v in man["timings"].items()]
    out = {
        "video": str(video) if truth is None else (f"{args.subject}, {args.size} px, {args.seconds:g} s"
                                                    + (", hair on the head" if args.hair == "head" else "")
                                                    + (f", head motion {args.motion}" if args.motion != "still" else "")
                                                    + (": its frames and audio without loss" if args.lossless else ": its H.264 video")),
        "frames": n,
        "pose_from": cfg.pose_from,
        "priors": cfg.priors,
        "pose_smooth": "auto" if cfg.pose_sigma is None else cfg.pose_sigma,
        "size": args.size,
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "cores": os.cpu_count(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "frames_per_s": round(n / wall, 1),
        "budget": (f"{BUDGET_S:g} s for 1500 frames at 512 px on 2 cores: {'within' if wall * 1500 / n <= BUDGET_S else 'over'} "
                   f"({wall * 1500 / n:.0f} s wall scaled to 1500 frames)") if args.size == 512 else "applies at --size 512 only",
        "rows": rows,
    }
    out.update({k: (round(v, 4) if isinstance(v, float) else v) for k, v in acc.items()})
    return out
