"""Training and evaluation data of the generic lip model (:mod:`lmgs.lips`): generated and real recordings.

Generated: the bundled generator's espeak-ng voices read its corpus, a few sentences a clip; the mouth
is what the generator animates (its articulation through a bundled head's deformation: the 68 points,
whose mouth is the truth). piper's voice ``joe`` is left out: it speaks the bundled subjects' own
training and test clips, which the model must not have heard. Each clip carries a low noise floor
(digital silence has no counterpart in a recording). Cached per :data:`CORPUS_VERSION` in
:func:`lmgs_eval.data.ingest.lips.cache_dir`.

Real: the lip tracks of :mod:`lmgs_eval.data.ingest.lips` (the dense mesh in the canonical face frame).

Both become :class:`lmgs.lips.LipSequence`: standardised log-mel windows and mouth deltas from the
recording's neutral mouth in units of its width.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

CORPUS_VERSION = 1
HEADS = ("astronaut", "hopper")
SENTENCES_PER_CLIP = 3
NOISE_DB = (-55.0, -35.0)  # the noise floor's range relative to the clip's speech RMS


@dataclass
class Recording:
    """One recording: 16 kHz audio, the 68 points per frame in the canonical frame ``[T, 68, 3]`` (NaN where
    untracked), and who speaks (a group: held out together)."""

    name: str
    audio: np.ndarray
    lms68: np.ndarray
    speaker: str
    sha256: str = ""  # of the video file a real recording was tracked from

    def provenance(self) -> dict:
        """What a lip model's provenance lists of a real recording it was adapted on (:func:`lmgs.lips_weights.adapted_on`)."""
        return {"clip": self.name, "sha256": self.sha256, "frames": int(len(self.lms68))}


def template68() -> np.ndarray:
    """MediaPipe's canonical face at the 68 points ``[68, 3]`` (metres, OpenCV axes): the lip model's frame."""
    from lmgs_eval.data.ingest.focal import canonical_face
    from lmgs_eval.data.ingest.lips import MESH_TO_68

    return canonical_face()[list(MESH_TO_68)]


def generated_recordings(progress=None) -> list[Recording]:
    """Every espeak-ng voice reading the whole corpus, :data:`SENTENCES_PER_CLIP` sentences a clip, the
    heads taking turns; cached. Deterministic (espeak-ng is, the noise is seeded)."""
    import zlib

    from lmgs.lips import similarity, STABLE
    from lmgs_eval.data.bundled import articulation as art_mod, speech as sp_mod
    from lmgs_eval.data.bundled.generator import head_model, load_corpus
    from lmgs_eval.data.ingest.lips import cache_dir

    f = cache_dir() / f"generated-v{CORPUS_VERSION}.npz"
    if f.is_file():
        z = np.load(f, allow_pickle=False)
        names = [str(s) for s in z["names"]]
        return [Recording(n, z[f"a{k}"], z[f"l{k}"], str(z["speakers"][k])) for k, n in enumerate(names)]
    corpus = load_corpus()
    sentences = [s for sec in ("train", "cross-a", "cross-b") for s in corpus[sec]]
    tpl = template68()
    st = list(STABLE)
    out: list[Recording] = []
    jobs = [(v, i) for v in sp_mod.ESPEAK_VOICES for i in range(0, len(sentences), SENTENCES_PER_CLIP)]
    for j, (voice, i) in enumerate(jobs):
        texts = sentences[i:i + SENTENCES_PER_CLIP]
        sp = sp_mod.synthesize(texts, f"espeak:{voice}")
        n = len(sp.audio) // 640
        key = f"{voice}:{i}"
        rng = np.random.default_rng([CORPUS_VERSION, zlib.crc32(key.encode())])
        art = art_mod.articulation(sp.phones, n, 25, rng)
        head = head_model(HEADS[j % len(HEADS)], 256)
        lms = np.stack([head.deform(a)[:68] for a in art])  # the head's own frame: no head pose in deform
        s, R, t = similarity(np.median(lms, 0)[st], tpl[st])
        lms = s * lms @ R.T + t
        audio = sp.audio[: n * 640].astype(np.float64)
        rms = float(np.sqrt((audio[np.abs(audio) > 1e-4] ** 2).mean())) if (np.abs(audio) > 1e-4).any() else 0.1
        level = 10 ** (rng.uniform(*NOISE_DB) / 20) * rms
        audio = np.clip(audio + level * rng.standard_normal(len(audio)), -1, 1).astype(np.float32)
        out.append(Recording(f"gen-{voice}-{i}", audio, lms.astype(np.float32), f"espeak:{voice}"))
        if progress is not None:
            progress(j + 1, len(jobs))
    f.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"names": np.array([r.name for r in out]), "speakers": np.array([r.speaker for r in out])}
    for k, r in enumerate(out):
        arrays[f"a{k}"], arrays[f"l{k}"] = r.audio, r.lms68
    tmp = f.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(f)
    return out


# Speakers of the development footage: one per clip (the four HDTF clips are four people; the four
# short_face clips were looked at and are four more).
def speaker_of(name: str) -> str:
    return name


def real_recordings(folder: str | Path, progress=None) -> list[Recording]:
    """The lip tracks of every ``*.mp4`` in ``folder`` (cached by :func:`lmgs_eval.data.ingest.lips.cached_track`)."""
    from lmgs.fileio import sha256_file
    from lmgs_eval.data.ingest.lips import cached_track

    out = []
    for p in sorted(Path(folder).glob("*.mp4")):
        tr = cached_track(p)
        out.append(Recording(p.stem, tr.audio, tr.lms68, speaker_of(p.stem), sha256_file(p)))
        if progress is not None:
            progress(p.name)
    return out


def features(audio: np.ndarray, n: int) -> np.ndarray:
    """lmgs's default front end (log-mel windows ``[n, 16, 80]``) of a 16 kHz waveform."""
    from lmgs.audio import compute_features

    return compute_features(audio, 16000, None, n_frames=n)


def sequences(rec: Recording, frames: slice | None = None):
    """A recording as :class:`lmgs.lips.LipSequence` pieces: the runs of tracked frames within ``frames`` (default all),
    with the neutral mouth, width and audio statistics of those frames."""
    from lmgs.lips import MOUTH, LipSequence, feature_stats, neutral_mouth, standardise

    n = len(rec.lms68)
    sl = frames or slice(0, n)
    feats = features(rec.audio, n)[sl]
    mouth = rec.lms68[sl, MOUTH].astype(np.float64)
    ok = np.isfinite(mouth).all(axis=(1, 2))
    neutral, width = neutral_mouth(mouth[ok])
    z = standardise(feats, feature_stats(feats))
    d = ((mouth - neutral) / width).astype(np.float32)
    out, k = [], 0
    while k < len(ok):
        if not ok[k]:
            k += 1
            continue
        e = k
        while e < len(ok) and ok[e]:
            e += 1
        if e - k >= 8:
            out.append(LipSequence(z[k:e], d[k:e]))
        k = e
    return out


# ----------------------------------------------------------------------------- the training recipe
# One recipe for the shipped weights (scripts/train_lip_model.py) and for every held-out fold of
# `lmgs-eval bench lips`, so the benchmark scores the way the shipped model was made.
SEED = 0
PRETRAIN = {"steps": 3000, "lr": 2e-3, "batch": 16, "length": 64}
ADAPT = {"steps": 300, "lr": 2e-4, "batch": 16, "length": 64, "extra_share": 0.5}


def pretrain(generated: list[Recording], progress=None):
    """A :class:`lmgs.lips.LipModel` trained from scratch on the generated recordings (:data:`PRETRAIN`)."""
    from lmgs.lips import new_model, train_lip_model

    seqs = [s for r in generated for s in sequences(r)]
    model = new_model(template68(), SEED)
    return train_lip_model(model, seqs, seed=SEED, progress=progress, **PRETRAIN)


def without_speakers(real: list[Recording], clips) -> list[Recording]:
    """``real`` without the recordings of the speakers of ``clips`` (names of recordings in ``real``); a name that
    is none of them is a ``ValueError``."""
    names = {r.name: r.speaker for r in real}
    unknown = [c for c in clips if c not in names]
    if unknown:
        raise ValueError(f"{', '.join(unknown)}: no such clip (the clips: {', '.join(sorted(names))})")
    gone = {names[c] for c in clips}
    return [r for r in real if r.speaker not in gone]


def adapt(pretrained, real: list[Recording], generated: list[Recording], progress=None):
    """A copy of ``pretrained`` adapted on the real recordings, a share of each batch still generated (:data:`ADAPT`)."""
    import copy

    from lmgs.lips import train_lip_model

    model = copy.deepcopy(pretrained)
    seqs = [s for r in real for s in sequences(r)]
    gen = [s for r in generated for s in sequences(r)]
    kw = dict(ADAPT)
    share = kw.pop("extra_share")
    return train_lip_model(model, seqs, seed=SEED + 1, extra=gen, extra_share=share, progress=progress, **kw)
