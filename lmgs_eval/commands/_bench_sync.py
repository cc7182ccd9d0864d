"""``lmgs-eval bench sync``: the mesh sync scorer's recipe on real footage, each speaker held out.

Reads the development footage (``--footage``, default ``../shared/footage``: videos of real people, never
copied anywhere; their lip tracks are cached outside the repository, :mod:`lmgs_eval.data.ingest.lips`). For
every speaker of the footage (a fold) the recipe of :mod:`lmgs_eval.metrics.sync.train.mesh` adapts the
landmark scorer's weights on the *other* speakers' recordings (and the generated ones), and that model
scores the held-out speaker's clips: each clip is scored by a model that never saw its speaker, as a
user's footage is.

Per clip (:func:`lmgs_eval.metrics.sync.train.mesh.evaluate`): the offset found on the clip as it is (in
sync: 0 expected), the offsets found with its audio delayed by -10, -5, +5 and +10 frames (``-k``
expected), its own LSE-C against the highest LSE-C with another speaker's speech in place of its own,
the self-check's separation and verdict, and whether the clip passes all of these. ``--clip`` runs only
the folds of the named clips' speakers (the other speakers still train each fold).

Beside it, unless ``--no-landmark``: the same figures for the shipped landmark scorer fed dlib's landmarks
on the same 25 fps frames (``landmark_dlib``; trained on generated clips only, so nothing is held out).

Deterministic for the seed and the thread count. Minutes a fold on two cores; one line a fold on standard
error.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

IN_ALL = False  # adapts a model per held-out speaker: `bench all` leaves it out
HELP = "the mesh sync scorer's recipe on real footage, each speaker held out (offsets, shifts, other speech)"
FOOTAGE = Path("../shared/footage")
SEED = 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--footage", default=str(FOOTAGE),
                   help=f"folder of real in-sync talking clips (*.mp4; default {FOOTAGE})")
    p.add_argument("--clip", action="append", default=[],
                   help="run only the fold of this clip's speaker (file stem; repeatable)")
    p.add_argument("--steps", type=int, default=None,
                   help="adaptation steps per fold (default: the recipe's, lmgs_eval.metrics.sync.train.mesh.ADAPT)")
    p.add_argument("--no-landmark", action="store_true",
                   help="leave out the landmark scorer fed dlib's landmarks on the same clips (the comparison)")


def _videos(folder: Path) -> list[Path]:
    """The folder's ``*.mp4``; a folder that is not there or holds none is a UserError naming the flag."""
    from lmgs_eval.errors import UserError

    if not folder.is_dir():
        raise UserError(f"--footage {folder}: no such folder; bench sync needs real in-sync talking clips (*.mp4)")
    videos = sorted(folder.glob("*.mp4"))
    if not videos:
        raise UserError(f"--footage {folder}: no *.mp4 here; bench sync needs real in-sync talking clips")
    return videos


def table_row(r: dict) -> dict:
    """One clip's row of the printed table."""
    row = {"clip": r["clip"], "speaker": r["speaker"], "offset": r["offset"]}
    for k, v in r["shifts"].items():
        row[f"delay {int(k):+d}"] = v
    row.update({"lse_c": r["lse_c"], "other_lse_c_max": r["other_lse_c_max"], "separation": r["separation"],
                "trusted": r["trusted"], "pass": r["passes"], "confident_wrong": r["confident_wrong"]})
    return row


def run(args: argparse.Namespace) -> dict:
    import torch

    from lmgs_eval.data.lip_corpus import real_recordings
    from lmgs_eval.errors import UserError
    from lmgs_eval.metrics.sync.train import mesh as T

    folder = Path(args.footage)
    _videos(folder)
    if args.steps is not None and args.steps < 1:
        raise UserError(f"--steps {args.steps}: adaptation needs at least one step")
    t0 = time.perf_counter()
    log = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    recs = real_recordings(folder)
    names = {r.name: r.speaker for r in recs}
    unknown = [c for c in args.clip if c not in names]
    if unknown:
        raise UserError(f"--clip {unknown[0]}: not among the clips of {folder} ({', '.join(sorted(names))})")
    speakers = T.folds(recs)
    if len(speakers) < 2:
        raise UserError(f"--footage {folder}: one speaker only ({speakers[0]}); leaving a speaker out needs two "
                        "or more")
    if args.clip:
        speakers = [s for s in speakers if s in {names[c] for c in args.clip}]
    adapt_kw = {} if args.steps is None else {"steps": int(args.steps)}
    generated = T.generated_inputs(SEED)
    rows = T.fold_rows(recs, speakers, SEED, generated, lambda line: log('bench sync: ' + line), **adapt_kw)
    summary = {k: v for k, v in T.summary(rows).items() if k != "per_clip"}
    extra = {}
    if not args.no_landmark:
        held = [r for r in recs if r.speaker in set(speakers)]
        lrows = T.landmark_rows(held, folder, lambda line: log("bench sync: " + line)) if held else []
        lsum = T.summary(lrows)
        extra = {"landmark_dlib_passes": lsum["passes"], "landmark_dlib_confident_wrong": lsum["confident_wrong"],
                 "landmark_dlib": [table_row(r) for r in lrows]}
    return {
        "footage": str(folder),
        "note": "leave one speaker out: each clip is scored by a model adapted without any recording of its speaker "
                "(the mesh scorer's recipe, lmgs_eval.metrics.sync.train.mesh); offset 0 expected in sync, -k with "
                "the audio delayed by k frames; other_lse_c_max is the highest LSE-C with another speaker's speech",
        "pass": "offset within 1, every delay found within 1, own LSE-C above every other speech's, self-check trusted",
        **summary,
        "folds": len(speakers),
        "steps": int(args.steps) if args.steps is not None else T.ADAPT["steps"],
        "seed": SEED,
        "threads": torch.get_num_threads(),
        "seconds": round(time.perf_counter() - t0, 1),
        "rows": [table_row(r) for r in rows],
        **extra,
    }
