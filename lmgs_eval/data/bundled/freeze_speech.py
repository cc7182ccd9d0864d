"""Write ``speech_frozen.xz``: the piper sentences of the default bundled subjects.

piper's ONNX Runtime kernels depend on the CPU's instruction set, so its audio differs by
a few 16-bit steps between a CPU with AVX-512 and one without; the shipped file makes the
bundled subjects the same bytes everywhere (see ``speech.py``). It was written on an AVX2
code path by running this module under qemu-user emulating a Haswell CPU::

    qemu-x86_64 -cpu Haswell .venv/bin/python -m lmgs_eval.data.bundled.freeze_speech --subject astronaut --out a.xz
    qemu-x86_64 -cpu Haswell .venv/bin/python -m lmgs_eval.data.bundled.freeze_speech --subject hopper --out h.xz
    python -m lmgs_eval.data.bundled.freeze_speech --merge a.xz h.xz

(Debian's qemu-user; about half an hour per subject, natively a few seconds; valgrind,
which also hides AVX-512, gave the same samples for a sentence checked both ways, four
times slower). Every sentence a default build speaks with piper is synthesised live here,
whatever the file already holds; ``--merge`` only joins files written so.
"""

from __future__ import annotations

import argparse
import platform
import sys
from pathlib import Path

import numpy as np

from lmgs_eval.data.bundled import generator as g
from lmgs_eval.data.bundled import speech as sp


def piper_texts(name: str, seconds: float = 60.0) -> dict[str, tuple[np.ndarray, list]]:
    """Synthesise (live) every sentence a build of ``name`` speaks with piper: ``{text: (pcm16, phones)}``."""
    done: dict[str, tuple[np.ndarray, list]] = {}
    live = sp._synth_piper

    def record(text: str):
        if text not in done:
            audio, phones, sr = live(text)
            done[text] = (sp.pcm16(sp._resample_to_16k(audio, sr)), phones)
        a, phones = done[text]
        return a.astype(np.float32) / sp.PCM_SCALE, phones, sp.SAMPLE_RATE

    corpus = g.load_corpus()
    train = corpus["train"]
    off = g.TEXT_OFFSET[name] % len(train)
    with _live_piper(record):
        sp.speak_for(train[off:] + train[:off], g.TRAIN_VOICE, int(round(seconds * g.FPS)) / g.FPS)
        cross_n = int(round(g._cross_seconds(seconds) * g.FPS))
        for voice, section in g.CROSS[name].values():
            if voice == sp.PIPER_VOICE:
                sp.speak_for(corpus[section], voice, cross_n / g.FPS)
    return done


class _live_piper:
    """Within the block, piper sentences go to ``fn`` and the frozen file is not read."""

    def __init__(self, fn):
        self.fn = fn

    def __enter__(self):
        self.saved = (sp._synth_piper, sp.frozen_piper)
        sp._synth_piper = self.fn
        sp.frozen_piper = lambda: {}
        return self

    def __exit__(self, *exc):
        sp._synth_piper, sp.frozen_piper = self.saved


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m lmgs_eval.data.bundled.freeze_speech", description=__doc__.split("\n")[0])
    p.add_argument("--subject", action="append", choices=sorted(g.TEXT_OFFSET), help="subjects (default: all bundled)")
    p.add_argument("--seconds", type=float, default=60.0, help="the build length whose sentences are frozen (default 60)")
    p.add_argument("--out", default=str(sp.FROZEN_PATH), help="file to write (default: the shipped one)")
    p.add_argument("--merge", nargs="+", metavar="FILE", help="join these frozen files (no synthesis)")
    args = p.parse_args(argv)
    entries: dict[str, tuple[np.ndarray, list]] = {}
    if args.merge:
        sources = []
        for f in args.merge:
            header, got = sp.decode_frozen(Path(f).read_bytes(), f)
            for text, e in got.items():
                if text in entries and not np.array_equal(entries[text][0], e[0]):
                    print(f"{f}: {text!r} differs from the other files' samples", file=sys.stderr)
                    return 1
                entries[text] = e
            sources.append(header["source"])
        return _write(args.out, entries, "; ".join(sorted(set(sources))))
    for name in args.subject or sorted(g.TEXT_OFFSET):
        entries.update(piper_texts(name, args.seconds))
        print(f"{name}: {len(entries)} sentences so far", file=sys.stderr)
    return _write(args.out, entries, f"piper {sp.PIPER_VOICE} live, onnxruntime {_ort_version()} on {_cpu()}")


def _write(out: str, entries: dict, source: str) -> int:
    from lmgs.fileio import atomic_write

    atomic_write(Path(out), sp.encode_frozen(entries, source))
    print(f"{out}: {len(entries)} sentences ({source})", file=sys.stderr)
    return 0


def _ort_version() -> str:
    import onnxruntime

    return onnxruntime.__version__


def _cpu() -> str:
    """Whether the CPU, as the program's CPUID sees it (under qemu: the emulated model), has AVX-512."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as feats
    except ImportError:  # numpy < 2
        from numpy.core._multiarray_umath import __cpu_features__ as feats
    return f"{platform.machine()} {'with' if feats.get('AVX512F') else 'without'} AVX-512 (CPUID as numpy saw it)"


if __name__ == "__main__":
    raise SystemExit(main())
