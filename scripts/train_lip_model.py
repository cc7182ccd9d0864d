"""Train the generic audio-to-lip model shipped in ``lmgs/lips_models/`` (see :mod:`lmgs.lips`).

    python scripts/train_lip_model.py [--footage ../shared/footage] [--out lmgs/lips_models] [--check]
    python scripts/train_lip_model.py --hold-out CLIP [CLIP ...] --out DIR


1. Generated data: the bundled generator's espeak-ng voices read its corpus (about 34 minutes; about a
   minute to make, cached): :func:`lmgs_eval.data.lip_corpus.generated_recordings`.
2. Pretraining on it (:data:`lmgs_eval.data.lip_corpus.PRETRAIN`) -> ``lips_generated.pt``.
3. Real lip tracks of the talking clips in ``--footage`` (the dense face mesh, cached outside the
   repository), and adaptation on all of them (:data:`lmgs_eval.data.lip_corpus.ADAPT`) -> ``lips_generic.pt``.

The clips adapted on are listed with their files' sha256 in ``provenance.json`` beside the weights: the
evaluation toolkit refuses to score a method reading the lip model on a clip it was adapted on.
``--hold-out CLIP ...`` makes weights for scoring on those clips: the shipped pretrained file
(``lips_generated.pt``, sha256 checked) adapted with the recipe above on the other speakers' clips only,
written to ``DIR/lips_generic.pt`` with ``DIR/lips_generic.pt.json`` (what it was adapted on and without);
lmgs reads them with ``--set train.landmark_source=generic --set train.lip_weights=DIR/lips_generic.pt``.

Deterministic: one thread, fixed seeds, torch's deterministic algorithms; the files' bytes depend on the
weights only. The sha256 of each file written is printed beside the one :data:`lmgs.lips_weights.WEIGHTS` records;
``--check`` exits 1 where they differ. A few minutes on one core (pretraining is most of it).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[1].strip())
    p.add_argument("--footage", default="../shared/footage", help="folder of real talking clips (*.mp4)")
    p.add_argument("--out", default=None, help="where to write the weights (default: lmgs/lips_models, the shipped ones)")
    p.add_argument("--check", action="store_true", help="exit 1 unless both files reproduce the recorded sha256")
    p.add_argument("--hold-out", nargs="+", default=[], metavar="CLIP",
                   help="adapt the shipped pretrained model without these clips' speakers (file stems), into --out")
    args = p.parse_args(argv)

    import torch

    from lmgs import lips, lips_weights
    from lmgs.fileio import sha256_file
    from lmgs_eval.data import lip_corpus

    footage = Path(args.footage)
    if not (footage.is_dir() and any(footage.glob("*.mp4"))):
        print(f"train_lip_model: error: {footage}: no talking clips (*.mp4) to adapt on (--footage FOLDER)", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else lips_weights.FOLDER
    if args.hold_out and (args.out is None or out.resolve() == lips_weights.FOLDER.resolve()):
        print("train_lip_model: error: --hold-out writes weights that are not the shipped ones: pass --out DIR "
              f"(not {lips_weights.FOLDER})", file=sys.stderr)
        return 2
    if args.hold_out and args.check:
        print("train_lip_model: error: --check compares the shipped weights; held-out weights have no recorded sha256",
              file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    t0 = time.perf_counter()
    say = lambda msg: print(f"[{time.perf_counter() - t0:6.0f} s] {msg}", flush=True)  # noqa: E731
    if args.hold_out:
        return hold_out(args.hold_out, footage, out, say)
    out.mkdir(parents=True, exist_ok=True)
    generated = lip_corpus.generated_recordings(progress=lambda j, n: say(f"generated {j}/{n}") if j % 50 == 0 or j == n else None)
    say(f"{len(generated)} generated clips, {sum(len(r.lms68) for r in generated) / 1500:.1f} min")
    pre = lip_corpus.pretrain(generated, progress=lambda s, l: say(f"pretrain step {s} loss {l:.2e}") if s % 500 == 0 else None)
    lips.save(pre, out / "lips_generated.pt")
    real = lip_corpus.real_recordings(footage, progress=lambda name: say(f"lip track {name}"))
    say(f"{len(real)} real clips, {sum(len(r.lms68) for r in real) / 1500:.1f} min, {len({r.speaker for r in real})} speakers")
    final = lip_corpus.adapt(pre, real, generated, progress=lambda s, l: say(f"adapt step {s} loss {l:.2e}") if s % 200 == 0 else None)
    lips.save(final, out / "lips_generic.pt")
    lips_weights.write_shipped_provenance(out, [r.provenance() for r in real])
    same = True
    for name in ("lips_generated.pt", "lips_generic.pt"):
        got, want = sha256_file(out / name), lips_weights.WEIGHTS[name][1]
        same &= got == want
        print(f"{out / name}: sha256 {got} ({'as recorded' if got == want else 'recorded: ' + (want or 'none')})")
    say(f"done; {lips.n_parameters(final)} parameters")
    return 1 if args.check and not same else 0


def hold_out(clips: list[str], footage: Path, out: Path, say) -> int:
    """The shipped pretrained model adapted without ``clips``' speakers, into ``out/lips_generic.pt`` (+ ``.json``)."""
    from lmgs import lips, lips_weights
    from lmgs.errors import InputError
    from lmgs.fileio import sha256_file
    from lmgs_eval.data import lip_corpus

    try:
        pre = lips.load("lips_generated.pt")
    except InputError as exc:
        print(f"train_lip_model: error: {exc}", file=sys.stderr)
        return 2
    real = lip_corpus.real_recordings(footage, progress=lambda name: say(f"lip track {name}"))
    try:
        kept = lip_corpus.without_speakers(real, clips)
    except ValueError as exc:
        print(f"train_lip_model: error: --hold-out {exc}", file=sys.stderr)
        return 2
    say(f"{len(kept)} of {len(real)} real clips kept ({', '.join(sorted(set(r.name for r in real) - set(r.name for r in kept)))} "
        "held out)")
    generated = lip_corpus.generated_recordings()
    final = lip_corpus.adapt(pre, kept, generated, progress=lambda s, l: say(f"adapt step {s} loss {l:.2e}") if s % 200 == 0 else None)
    path = out / "lips_generic.pt"
    out.mkdir(parents=True, exist_ok=True)
    lips.save(final, path)
    lips_weights.write_provenance(path, [r.provenance() for r in kept], held_out=sorted(clips))
    print(f"{path}: sha256 {sha256_file(path)}")
    say("done")
    return 0


if __name__ == "__main__":
    sys.exit(main())
