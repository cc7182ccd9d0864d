"""``lmgs-eval prepare``: build a bundled subject (or check a real one) in the data root."""

from __future__ import annotations

import argparse
import time

HELP = "build a bundled subject (astronaut, hopper) or check a processed subject folder"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--subject", default="astronaut", help="bundled name, folder name under the data root, or a path")
    p.add_argument("--size", type=int, default=None, help="frame size in pixels for a bundled subject (default 256)")
    p.add_argument("--seconds", type=float, default=None, help="duration for a bundled subject (default 60)")
    p.add_argument("--seed", type=int, default=0, help="generator seed for a bundled subject")
    p.add_argument("--data-root", help="folder of subjects (default: $LMGS_DATA or ~/.cache/lmgs/data)")
    p.add_argument("--force", action="store_true", help="rebuild a bundled subject even if cached")
    p.add_argument("--preview", action="store_true", help="also write a short mp4 with sound to watch")


def run(args: argparse.Namespace) -> int:
    from lmgs_eval.commands._common import check_seeds
    from lmgs_eval.data.layout import check_jpegs, read_subject
    from lmgs_eval.data.bundled_spec import BundledSpec
    from lmgs_eval.data.registry import ensure_bundled, resolve_subject_dir

    check_seeds([args.seed])
    t0 = time.perf_counter()
    spec = BundledSpec.parse(args.subject)
    if spec is not None:
        spec = BundledSpec(
            spec.name,
            args.size if args.size is not None else spec.size,
            args.seconds if args.seconds is not None else spec.seconds,
            args.seed or spec.seed,
        )
        folder = ensure_bundled(spec, args.data_root, force=args.force)
    else:
        if args.size is not None or args.seconds is not None:
            from lmgs_eval.errors import UserError

            raise UserError(f"--size/--seconds apply to bundled subjects only, not '{args.subject}'")
        folder = resolve_subject_dir(args.subject, args.data_root)
    subject = read_subject(folder)
    check_jpegs(folder)  # every frame, not only the first that read_subject decodes
    d = subject.describe()
    print(f"{subject.name}: {d['frames']} frames {d['width']}x{d['height']} at {d['fps']} fps "
          f"({d['seconds']:.1f} s), split {d['train_frames']} train / {d['test_frames']} test, at {folder} "
          f"[{time.perf_counter() - t0:.1f} s]")
    if subject.bundled:
        print(f"  stand-in: {subject.meta.get('standin', 'synthetic bundled subject')}")
    if subject.budget_density is not None:
        print(f"  Gaussian budget: {subject.budget_density:g} per face pixel for the methods sized by face area "
              "(this subject's capacity knee, not the quick preset's)")
    from lmgs_eval.protocols.plate import plate_reference_psnr

    ceiling = plate_reference_psnr(subject)
    if ceiling is not None:
        print(f"  plate: the test frames' head (parsing) composited on the plate (torso_imgs over bc.jpg) scores PSNR "
              f"{ceiling:.2f} dB: the best a renderer drawing only the head can reach here (Table I's 'GT head on plate')")
    for note in subject.notes:
        print(f"  note: {note}")
    if args.preview:
        from lmgs_eval.data import bundled

        out = bundled.make_preview(folder, folder / "preview.mp4")
        print(f"  preview: {out}")
    return 0
