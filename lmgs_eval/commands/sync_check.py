"""``lmgs-eval sync-check``: probe the sync scorer on footage you know is in sync."""

from __future__ import annotations

import argparse
import json

HELP = ("check the LSE scorer on an in-sync clip: offset, injected audio shifts, other speech "
        "(tells whether its LSE can be believed on footage like yours)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lmgs_eval.commands._sync import add_sync_argument

    p.add_argument("video", help="a video with its own audio track, in sync (25 fps)")
    p.add_argument("--audio", help="the clip's audio, when the video has no track")
    p.add_argument("--other-audio", help="other speech (any wav, looped when shorter than the clip; at least 2 s or the "
                                         "clip's length): the clip's LSE-C must stay clearly above it")
    p.epilog = ("LSE is all sync-check measures: when it cannot be computed (no face, no or too little audio, no "
                "scorer) that is one error line and exit code 2.")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    add_sync_argument(p)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from lmgs_eval.commands._sync import suite
    from lmgs_eval.data.audio import load_audio
    from lmgs_eval.errors import UserError
    from lmgs_eval.data.frames import FrameFile
    from lmgs_eval.metrics.suite import clip_audio
    from lmgs_eval.metrics.sync.crops import FaceClip
    from lmgs_eval.metrics.sync.probe import check_other, probe

    lse = suite(args).metric("lse")  # the --sync scorer, resolved once
    src = FrameFile(args.video)  # frames are read as the scorer needs them, never held whole
    if src.fps is not None and abs(src.fps - 25.0) > 0.01:
        raise UserError(f"{args.video}: {src.fps:g} fps; the sync scorers read 25 fps")
    if args.audio is None and src.audio is None:
        raise UserError(f"{args.video}: no audio track; give --audio")
    a16, reason, _ = clip_audio(args.audio, src)
    if a16 is None:
        raise UserError(reason)
    other = None
    if args.other_audio:
        other = load_audio(Path(args.other_audio))[0]
        check_other(other, len(a16), f"--other-audio {args.other_audio}")
    out = probe(FaceClip(src), a16, lse.score, other)
    if not out["available"]:
        raise UserError(f"{args.video}: LSE unavailable: {out['reason']}")
    if args.json:
        print(json.dumps(out, indent=2, default=str))
        return 0
    o = out["own"]
    print(f"scorer: {out['backend']}")
    print(f"own audio: offset {o['offset']:+d}, LSE-C {o['lse_c']:.3f}, LSE-D {o['lse_d']:.3f}, separation "
          + (f"{o['separation']:.2f}" if o["separation"] is not None else "n/a") + f", trusted {o['trusted']}")
    print("injected delays: " + ", ".join(f"{k:+d} -> offset {v:+d}" for k, v in out["shifts"].items())
          + f" ({out['shifts_within_1']}/{len(out['shifts'])} within 1 frame of -k)")
    if "other_lse_c" in out:
        print("other speech LSE-C: " + ", ".join(f"{c:.3f}" for c in out["other_lse_c"])
              + f" (own above every one: {out['own_above_every_other']})")
    for f in out["flags"]:
        print(f"flag: {f}")
    return 0
