"""``lmgs-eval ingest VIDEO``: make a processed subject from a raw talking-head video."""

from __future__ import annotations

import argparse
import json
import time

HELP = "make a subject in the ER-NeRF / TalkingGaussian layout from a raw talking-head video (CPU, offline)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lmgs_eval.data.ingest import IngestConfig

    p.add_argument("video", help="the video (any format ffmpeg reads; audio from its own track unless --audio)")
    p.add_argument("--audio", help="speech to use instead of the video's own track (WAV or any audio file)")
    p.add_argument("--name", help="subject name (default: the video's file name without extension)")
    p.add_argument("--size", type=int, default=512, help="output frame side in pixels (default 512)")
    p.add_argument("--crop", choices=("auto", "head", "none"), default="auto",
                   help="auto: a fixed square window around the head unless the video already is a head crop (default)")
    p.add_argument("--focal", type=float, default=None, help="focal length in output pixels (default: searched over the clip)")
    p.add_argument("--pose-from", choices=("mesh", "landmarks"), default=IngestConfig.pose_from,
                   help="each frame's head pose from the subject's shape fitted to the dense face mesh, or from the "
                        f"68-point template on dlib's landmarks (default {IngestConfig.pose_from})")
    p.add_argument("--priors", choices=("ellipsoid", "mesh"), default=IngestConfig.priors,
                   help="depth / normal priors: the posed head ellipsoid, or the tracked face mesh over the face and the "
                        f"head ellipsoid beyond it (default {IngestConfig.priors})")
    p.add_argument("--pose-smooth", default=None, metavar="auto|FRAMES",
                   help="the poses' smoothing over time: auto (Whittaker's smoother, its weight chosen by generalised "
                        "cross-validation) or a Gaussian's sigma in frames (0: none); default "
                        f"{'auto' if IngestConfig.pose_sigma is None else IngestConfig.pose_sigma}")
    p.add_argument("--data-root", help="folder of subjects (default: $LMGS_DATA or ~/.cache/lmgs/data)")
    p.add_argument("--preview", action="store_true", help="also write preview.png: a contact sheet of frames, landmarks, masks, plate and pose axes")
    p.add_argument("--force", action="store_true", help="replace an existing subject of that name")
    p.add_argument("--jobs", type=int, default=None, help="processes for the per-frame stages (default: CPU count, at most 4)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    from lmgs_eval.data.ingest import IngestConfig, ingest

    t0 = time.perf_counter()
    from lmgs_eval.data.ingest.pipeline import pose_sigma_from

    smooth = {} if args.pose_smooth is None else {"pose_sigma": pose_sigma_from(args.pose_smooth)}
    cfg = IngestConfig(size=args.size, crop=args.crop, focal=args.focal, pose_from=args.pose_from, priors=args.priors, **smooth)
    folder = ingest(args.video, args.name, audio=args.audio, data_root=args.data_root, cfg=cfg, force=args.force,
                    progress=not args.quiet, jobs=args.jobs)
    man = json.loads((folder / "manifest.json").read_text())
    fr, ps = man["frames"], man["pose"]
    print(f"{folder.name}: {fr['kept']} frames {args.size}x{args.size} at 25 fps ({fr['kept'] / 25:.1f} s; "
          f"{fr['without_face']} without a detected face, interpolated) at {folder} [{time.perf_counter() - t0:.1f} s]")
    print(f"  focal {ps['focal']:.0f} px ({ps['focal_widths']:.2f} frame widths); pitch/yaw/roll "
          f"{ps['pitch_yaw_roll_deg_min']} .. {ps['pitch_yaw_roll_deg_max']} deg; reprojection {ps['reprojection_px_mean']:.2f} px")
    print("  " + ", ".join(f"{k} {v['frames_per_s']} frames/s" for k, v in man["timings"].items()))
    for k, v in man["flags"].items():
        print(f"  flag {k}: {v}")
    for note in man["notes"]:
        print(f"  note: {note}")
    if args.preview:
        from lmgs_eval.data.ingest.preview import contact_sheet

        print(f"  preview: {contact_sheet(folder, folder / 'preview.png')}")
    print(f"  next: lmgs-eval prepare --subject {folder.name}" + (f" --data-root {args.data_root}" if args.data_root else ""))
    return 0
