"""``lmgs-eval bench stripped``: one method on a bundled subject, and on its copy stripped to a plain folder.

The bundled subject carries what its generator knows (``lms3d.npy``, rendered ``depth/`` and
``normal/`` maps). Its copy holds only what the field's preprocessing leaves
(:data:`complete.PLAIN_LAYOUT`), and reading it derives 3D landmarks and a head prior
(:mod:`complete`). The method is built once from the full subject (same preset, ``--set``
changes, seed and Gaussian budget: one config hash), trained afresh on each folder's
training split in a temporary folder, rendered from the test split's audio and scored by
the run's metric suite, as ``lmgs-eval self`` runs it. The figures are printed side by side
with ``stripped - full``; both ground truths are the same frames (checked).

The defaults are the full-size run: the bundled 60 s at 256 px, the ``quick`` preset (two
trainings of 4-10 minutes each on 2 cores, see ``docs/benchmark.md``). ``--seconds``,
``--size`` and ``--set train.*=N`` make it smaller. Records go to a temporary store unless
``--results`` keeps them.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

IN_ALL = False  # two trainings at its defaults, not a speed benchmark: `bench all` leaves it out
HELP = "a method trained on a bundled subject and on its copy stripped to a plain processed folder, side by side"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lmgs_eval.commands._bench_pair import add_arguments as pair_arguments

    pair_arguments(p)


def run(args: argparse.Namespace) -> dict:
    import numpy as np

    from lmgs_eval.commands import _bench_pair as pair
    from lmgs_eval.data.complete import derive, strip_to_plain
    from lmgs_eval.data.registry import ensure_bundled

    spec = pair.bundled_spec(args)
    t0 = time.perf_counter()
    full_root = ensure_bundled(spec, args.data_root, progress=False)
    build_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory(prefix="lmgs-bench-stripped-") as tmp:
        tmp = Path(tmp)
        results = Path(args.results) if args.results else tmp / "results"
        plain_root = strip_to_plain(full_root, tmp / f"{spec.folder}-plain")
        runs = {"full": pair.prepare(full_root), "stripped": pair.prepare(plain_root)}
        full, plain = runs["full"], runs["stripped"]
        if not np.array_equal(full["test"].frames, plain["test"].frames):
            raise RuntimeError(f"{plain_root}: the stripped copy's test frames differ from {full_root}'s")
        s = plain["subject"]
        # what the derivation itself costs (the read above may have found it cached)
        t0 = time.perf_counter()
        derive(plain_root, s.landmarks, s.c2w, s.focal, s.cx, s.cy, cache_dir=tmp / "derived")
        derive_s = time.perf_counter() - t0
        _, config_hash = pair.train_both(args, runs, tmp, results, "stripped")
        rec = plain["record"]
        out = {
            "subject": f"{spec.folder} ({spec.size} px, {spec.seconds:g} s, bundled; built in {build_s:.1f} s)",
            "full": str(full_root),
            "stripped": f"{plain_root} (removed at the end)",
            "method": f"{args.method} (preset {args.preset}, config {config_hash}, seed {args.seed}"
                      + (f", --set {' '.join(args.overrides)}" if args.overrides else "") + ")",
            "frames": f"{len(full['train'])} train / {len(full['test'])} test, {full['subject'].width} px",
            "derived": next((n for n in rec.notes if "derived 3D landmarks" in n), "nothing derived"),
            "derive_s": round(derive_s, 3),
            "lpips": getattr(rec.metrics.get("lpips"), "backend", None),
            "cores": os.cpu_count(),
            "load_avg_1min": round(os.getloadavg()[0], 2),
            "results": str(results) if args.results else "temporary (--results keeps the records)",
            "rows": pair.rows(full, plain, ("full", "stripped")),
        }
    return out
