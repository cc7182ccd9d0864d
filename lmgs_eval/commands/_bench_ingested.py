"""``lmgs-eval bench ingested``: one method on a bundled subject, and on the ingest of its own raw video.

The bundled generator writes each subject's raw video (``<name>.mp4``, with audio) beside the
processing it made from its own knowledge (exact masks, poses, landmarks). Here that video
is ingested (``lmgs-eval ingest``, uncropped, at the subject's size) into a temporary data
root, and the method is trained on both folders as ``bench stripped`` does
(:mod:`lmgs_eval.commands._bench_pair`): each run is scored against its own folder's ground
truth, as ``lmgs-eval self`` would score it. A third folder, ``decoded``, is the generator's
processing with the decoded video's frames in place of its exact ones: the generator's folder
holds frames no video carries (the raw video is H.264 at CRF 18, 4:2:0), and "decoded -
generator" is what the video costs the generator's processing. It is not the same for the
ingest's, whose ``gt_imgs`` replace the codec's noise outside the person with its plate: to
measure the processing alone, use ``--video lossless`` (below).

Each folder's ground truth is its own: the ingest's ``gt_imgs`` hold its plate outside the
person (as ER-NeRF's processing writes them), the generator's the frames themselves. ``PSNR
against the generator's frames`` scores every folder's renders against one ground truth, the
generator's test frames, which the ingest's frames line up with pixel for pixel.

Besides the full-frame figures, ``PSNR away from the head outline`` leaves out the pixels
within ``--band`` pixels of either folder's head outline, in both runs. The outline decides
which pixels of a test frame its own torso layer supplies and which the method renders, and
the two folders draw it differently (the generator's head layer is narrower than the head it
shows); the figure says how much of the full-frame difference lives there
(``lmgs_eval/data/ingest/design.md``, "End to end").

``--swap cameras`` / ``--swap geometry`` add a folder each: the ingest with the generator's
cameras and 3D landmarks (its depth maps moved to the generator's camera distance, their shape
kept), or with those and the generator's depth and normal maps as well. They say how much of
the gap the ingest's geometry leaves, and which part of it. The cameras and the 3D landmarks
share a world frame, so ``cameras`` swaps both; ``--swap landmarks`` takes the generator's 3D
landmarks alone, carried into the ingest's world frame by the one similarity (scale, rotation,
shift over every frame and point) that best lays them on the ingest's own, and keeps the
ingest's cameras: what the landmarks' motion carries, apart from the cameras.

``--video lossless`` ingests, instead of the raw video, the generator's frames (``ori_imgs``)
and audio encoded without loss (x264's RGB encoder at quantiser 0): the ingest then starts from
exactly the frames the generator's folder holds, "ingested - generator" is its processing alone,
and the ``decoded`` folder, which would be the generator's own, is not trained.

Defaults: the bundled 60 s at 256 px, the ``quick`` preset (an ingest of about a minute and
three trainings of 4-10 minutes each on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

IN_ALL = False  # an ingest and three trainings, not a speed benchmark: `bench all` leaves it out
HELP = "a method trained on a bundled subject and on the ingest of its raw video, side by side"
BAND_PX = 4
SWAPS = {  # what each --swap folder takes from the generator
    "cameras": "cameras and 3D landmarks, its depth maps moved to the generator's camera distance",
    "geometry": "cameras, 3D landmarks, depth and normal maps",
    "landmarks": "3D landmarks, carried into the ingest's world frame by one similarity (its cameras kept)",
}
CAMERA_FILES = ("transforms_train.json", "transforms_val.json", "track_params.pt", "lms3d.npy")  # one world frame


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lmgs_eval.commands._bench_pair import add_arguments as pair_arguments

    pair_arguments(p)
    p.add_argument("--hair", choices=("layer", "head"), default="layer",
                   help="layer: the bundled subject as built, whose hair beyond the head outline is a still layer the "
                        "generator's parsing calls torso; head: a copy built (in the temporary folder) with all the hair "
                        "moving with the head, as on a camera (default layer)")
    p.add_argument("--swap", action="append", choices=SWAPS, default=[],
                   help="also train on the ingest with the generator's cameras and 3D landmarks (cameras), with those "
                        "and its depth and normal maps (geometry), or with its 3D landmarks alone in the ingest's world "
                        "frame (landmarks); repeatable")
    p.add_argument("--video", choices=("h264", "lossless"), default="h264",
                   help="h264: ingest the generator's raw video (CRF 18, 4:2:0) as a camera's would come; lossless: its "
                        "frames and audio re-encoded without loss, so that only the ingest's processing differs "
                        "(default h264)")
    p.add_argument("--priors", choices=("ellipsoid", "mesh"), default=None,
                   help="the ingest's depth / normal priors (default: the ingest's own default)")
    p.add_argument("--band", type=int, default=BAND_PX,
                   help=f"half width in pixels of the band around each head outline left out of the second PSNR (default {BAND_PX})")


def decoded_copy(truth_root: Path, ing_root: Path, out: Path) -> Path:
    """The generator's folder with the ingest's frames (the raw video decoded, uncropped, at the
    same size) as its ``ori_imgs`` and ``gt_imgs``: the generator's exact processing fed what any
    processing of the video starts from. Against it, the ingest's figures show its processing;
    against the generator's own folder, the video's compression as well."""
    import shutil

    shutil.copytree(truth_root, out, ignore=shutil.ignore_patterns("*.jpg", "*.mp4", "cross"))
    shutil.copy2(truth_root / "bc.jpg", out / "bc.jpg")
    for src in (ing_root / "ori_imgs").glob("*.jpg"):
        shutil.copy2(src, out / "ori_imgs" / src.name)
        shutil.copy2(src, out / "gt_imgs" / src.name)
    return out


def swapped_copy(truth_root: Path, ing_root: Path, out: Path, part: str) -> Path:
    """The ingest's folder with the generator's geometry: ``cameras``: its cameras and 3D landmarks
    (which share its world frame), the ingest's depth maps shifted per frame so that their median
    is the generator's (the two cameras stand at different distances); ``geometry``: its depth and
    normal maps as well; ``landmarks``: its 3D landmarks alone, in the ingest's world frame
    (:func:`landmarks_in_frame_of`)."""
    import shutil

    from lmgs_eval.data.geometry import DEPTH_SCALE
    from lmgs_eval.data.images import read_depth, write_depth

    if part not in SWAPS:
        raise ValueError(f"part {part!r}: one of {tuple(SWAPS)}")
    shutil.copytree(ing_root, out, ignore=shutil.ignore_patterns("*.mp4"))
    if part == "landmarks":
        theirs, mine = np.load(truth_root / "lms3d.npy"), np.load(ing_root / "lms3d.npy")
        np.save(out / "lms3d.npy", landmarks_in_frame_of(theirs, mine).astype(np.float32))
        return out
    for name in CAMERA_FILES:
        shutil.copy2(truth_root / name, out / name)
    if part == "geometry":
        for d in ("depth", "normal"):
            shutil.rmtree(out / d)
            shutil.copytree(truth_root / d, out / d)
        # the generator's maps are its rendered head: measured, not derived (Subject.priors_derived)
        meta = json.loads((out / "meta.json").read_text())
        meta.update(priors_derived=False, depth=f"the generator's depth maps ({truth_root.name})",
                    normal=f"the generator's normal maps ({truth_root.name})")
        (out / "meta.json").write_text(json.dumps(meta, indent=1))
        return out
    for path in sorted((out / "depth").glob("*.png")):
        mine, theirs = read_depth(path, DEPTH_SCALE), read_depth(truth_root / "depth" / path.name, DEPTH_SCALE)
        if (mine > 0).any() and (theirs > 0).any():
            shift = np.median(theirs[theirs > 0]) - np.median(mine[mine > 0])
            write_depth(path, np.where(mine > 0, np.maximum(mine + shift, 1.0 / DEPTH_SCALE), 0.0), DEPTH_SCALE)
    return out


def landmarks_in_frame_of(theirs: np.ndarray, mine: np.ndarray) -> np.ndarray:
    """3D landmarks ``theirs`` ``[N, 68, 3]`` carried into the world frame of ``mine`` (the same
    frames) by the least-squares similarity over every frame and point: one scale, rotation and
    shift for the clip, so their motion from frame to frame is theirs alone."""
    from lmgs.lips import similarity

    theirs, mine = np.asarray(theirs, np.float64), np.asarray(mine, np.float64)
    if theirs.shape != mine.shape:
        raise ValueError(f"3D landmarks of shapes {theirs.shape} and {mine.shape}: not the same frames")
    s, rot, t = similarity(theirs.reshape(-1, 3), mine.reshape(-1, 3))
    return s * theirs @ rot.T + t


def run(args: argparse.Namespace) -> dict:
    from lmgs_eval.commands import _bench_pair as pair
    from lmgs_eval.data.ingest import IngestConfig, ingest
    from lmgs_eval.data.ingest.compare import bundled_truth, compare, edge_band, head_masks, lossless_video
    from lmgs_eval.errors import UserError
    from lmgs_eval.metrics.image import psnr_outside

    if not 0 <= args.band <= 64:
        raise UserError(f"--band {args.band}: must be between 0 and 64 pixels")
    spec = pair.bundled_spec(args)
    with tempfile.TemporaryDirectory(prefix="lmgs-bench-ingested-") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        truth_root = bundled_truth(spec, args.hair, tmp, args.data_root)
        build_s = time.perf_counter() - t0
        results = Path(args.results) if args.results else tmp / "results"
        video = truth_root / f"{spec.name}.mp4"
        if args.video == "lossless":
            video = lossless_video(truth_root, tmp / "lossless" / video.name)
        t0 = time.perf_counter()
        ing_root = ingest(video, f"{spec.folder}-ingested", data_root=tmp / "data",
                          cfg=IngestConfig(size=spec.size, crop="none", **({"priors": args.priors} if args.priors else {})),
                          progress=False)
        ingest_s = time.perf_counter() - t0
        man = json.loads((ing_root / "manifest.json").read_text())
        gen = pair.prepare(truth_root)
        n_truth = gen["subject"].n_frames
        if man["frames"]["first_source_frame"] != 0 or man["frames"]["kept"] != n_truth:
            raise UserError(f"{ing_root}: the ingest kept frames {man['frames']['first_source_frame']}.."
                            f"{man['frames']['first_source_frame'] + man['frames']['kept'] - 1} of {n_truth}: "
                            "the two folders' frames do not line up")
        runs = {"generator": gen}
        if args.video == "h264":
            dec_root = decoded_copy(truth_root, ing_root, tmp / "decoded" / f"{spec.folder}-decoded")
            runs["decoded"] = pair.prepare(dec_root)
        runs["ingested"] = pair.prepare(ing_root)
        parts = {f"ingested, generator's {part}": part for part in dict.fromkeys(args.swap)}
        swapped = {label: swapped_copy(truth_root, ing_root, tmp / "swap" / f"{spec.folder}-{part}", part)
                   for label, part in parts.items()}
        runs.update({label: pair.prepare(root) for label, root in swapped.items()})
        ing = runs["ingested"]
        bases = [label for label in ("generator", "decoded") if label in runs]
        acc = compare(truth_root, ing_root)
        _, config_hash = pair.train_both(args, runs, tmp, results, "ingested")
        ids = gen["subject"].test_ids
        band = edge_band(head_masks(truth_root, ids), args.band) | edge_band(head_masks(ing_root, ids), args.band)
        away, true = {}, {}
        for label, r in runs.items():
            frames = r["method"].render(r["driving"])  # the frames fit_render_score scored (rendering is deterministic)
            away[label] = psnr_outside(frames, r["test"].frames, band)
            true[label] = psnr_outside(frames, gen["test"].frames, np.zeros_like(band))
        swap_rows = {label: {r["figure"]: r[label] for r in pair.rows(ing, runs[label], ("ingested", label))} for label in swapped}
        rows = []
        for pairs in zip(*(pair.rows(runs[b], ing, (b, "ingested")) for b in bases)):
            rows.append({"figure": pairs[0]["figure"], **{b: p[b] for b, p in zip(bases, pairs)},
                         "ingested": pairs[0]["ingested"],
                         **{f"ingested - {b}": p[f"ingested - {b}"] for b, p in zip(bases, pairs)},
                         **{label: swap_rows[label][pairs[0]["figure"]] for label in swapped},
                         "note": next((p["note"] for p in pairs if p["note"]), "")})

        def side_row(figure: str, psnrs: dict, note: str) -> dict:
            return {"figure": figure, **{label: psnrs[label] for label in (*bases, "ingested")},
                    **{f"ingested - {b}": psnrs["ingested"] - psnrs[b] for b in bases},
                    **{label: psnrs[label] for label in swapped}, "note": note}

        rows[1:1] = [side_row(f"PSNR dB away from the head outlines (+-{args.band} px)", away,
                              f"{100 * band.mean():.1f} % of the test pixels left out"),
                     side_row("PSNR dB against the generator's frames", true,
                              "every folder's renders against one ground truth: the generator's test frames (the ingest's "
                              "own holds the plate outside the person)")]
        rec = ing["record"]
        out = {
            "subject": (f"{spec.folder} ({spec.size} px, {spec.seconds:g} s, bundled"
                        + (", all hair moving with the head" if args.hair == "head" else "") + f"; built in {build_s:.1f} s)"),
            "generator": str(truth_root),
            "video": (f"{video.name}: the generator's raw video (H.264 CRF 18, 4:2:0)" if args.video == "h264" else
                      f"{video.name}: the generator's frames and audio re-encoded without loss (H.264 RGB, quantiser 0)"),
            **({"decoded": f"{dec_root}: the generator's folder with the video's decoded frames (the ingest's ori_imgs) as "
                           "its frames"} if "decoded" in runs else {}),
            "ingested": f"{ing_root} (removed at the end; ingested in {ingest_s:.1f} s, ingest version {man['ingest_version']}, "
                        f"{man['parameters'].get('priors', 'ellipsoid')} priors)",
            **{label: f"{root}: the ingest with the generator's {SWAPS[parts[label]]}" for label, root in swapped.items()},
            "ingest accuracy": (f"landmarks {acc['landmark_px']:.2f} px, rotation {acc['rotation_deg']:.2f} deg, "
                                f"head IoU {acc['head_iou']:.3f}, person IoU {acc['person_iou']:.3f}, plate {acc['plate_psnr']:.1f} dB, "
                                f"gt_imgs against the true frames {acc['gt_psnr']:.1f} dB"),
            "method": f"{args.method} (preset {args.preset}, config {config_hash}, seed {args.seed}"
                      + (f", --set {' '.join(args.overrides)}" if args.overrides else "") + ")",
            "frames": f"{len(gen['train'])} train / {len(gen['test'])} test, {gen['subject'].width} px",
            "lpips": getattr(rec.metrics.get("lpips"), "backend", None),
            "cores": os.cpu_count(),
            "load_avg_1min": round(os.getloadavg()[0], 2),
            "results": str(results) if args.results else "temporary (--results keeps the records)",
            "rows": rows,
        }
    return out
