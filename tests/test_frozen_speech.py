"""The shipped piper sentences (``speech_frozen.xz``): what makes a bundled subject the
same bytes on every CPU.

References: the file's own sha256 of its samples, the WAV a build writes (read with the
standard ``wave`` module), and piper itself run live on this machine.
"""

from __future__ import annotations

import importlib.util
import wave

import numpy as np
import pytest

import lmgs_eval.data.bundled.generator as g
import lmgs_eval.data.bundled.speech as sp
from lmgs_eval.errors import UserError


def test_round_trip_and_damage(tmp_path):
    rng = np.random.default_rng(0)
    entries = {"Hello there.": (rng.integers(-32767, 32768, 1234).astype(np.int16), [("h", 0.0, 0.1), ("", 0.1, 0.2)]),
               "Bob.": (np.array([0, 32767, -32767, 5], np.int16), [("b", 0.0, 0.05)])}
    blob = sp.encode_frozen(entries, "test")
    header, out = sp.decode_frozen(blob)
    assert header["samples"] == 1238 and set(out) == set(entries)
    for t, (pcm, phones) in entries.items():
        assert np.array_equal(out[t][0], pcm) and out[t][1] == phones
    raw = bytearray(__import__("lzma").decompress(blob))
    raw[-3] ^= 0x40  # one sample byte changed
    with pytest.raises(UserError, match=r"x\.xz: samples do not match their sha256"):
        sp.decode_frozen(__import__("lzma").compress(bytes(raw)), "x.xz")
    with pytest.raises(UserError, match=r"y\.xz: not a frozen-speech file"):
        sp.decode_frozen(b"garbage", "y.xz")


def test_pcm16_is_what_the_writers_store(tmp_path):
    from lmgs_eval.data.audio import write_wav

    x = np.array([-1.5, -1.0, -0.5, 0.0, 1e-6, 0.3333, 0.99999, 1.0, 2.0], np.float32)
    q = sp.pcm16(x)
    assert q.tolist() == [-32767, -32767, -16384, 0, 0, 10921, 32767, 32767, 32767]
    # write_wav writes exactly these steps, for the (clipped, as the generator's) float audio and
    # for the audio rebuilt from them
    for audio in (np.clip(x, -1, 1), q.astype(np.float32) / sp.PCM_SCALE):
        write_wav(tmp_path / "a.wav", audio)
        with wave.open(str(tmp_path / "a.wav")) as w:
            assert np.frombuffer(w.readframes(w.getnframes()), "<i2").tolist() == q.tolist()


@pytest.mark.parametrize("name", sorted(g.TEXT_OFFSET))
def test_default_builds_speak_only_shipped_piper_sentences(name, monkeypatch):
    """A default (60 s) build of every bundled subject needs no live piper call."""
    assert sp.FROZEN_PATH.is_file()

    def live(text):
        raise AssertionError(f"not in speech_frozen.xz: {text!r}")

    monkeypatch.setattr(sp, "_synth_piper", live)
    corpus = g.load_corpus()
    train = corpus["train"]
    off = g.TEXT_OFFSET[name] % len(train)
    speech, used = sp.speak_for(train[off:] + train[:off], g.TRAIN_VOICE, 60.0)
    assert speech.seconds >= 60.0 and len(used) >= 10
    for voice, section in g.CROSS[name].values():
        if voice == sp.PIPER_VOICE:
            s, _ = sp.speak_for(corpus[section], voice, g._cross_seconds(60.0))
            assert s.seconds >= g._cross_seconds(60.0)


@pytest.mark.skipif(importlib.util.find_spec("piper") is None, reason="piper-tts not installed")
def test_shipped_sentences_are_what_piper_says():
    """Live piper on this CPU against the shipped samples: the same length and phones, and
    the samples equal but for the odd one-step difference of another kernel path (exactly
    equal on an AVX2 CPU)."""
    header, entries = sp.decode_frozen(sp.FROZEN_PATH.read_bytes())
    texts = sorted(entries)[:2]
    for text in texts:
        audio, phones, sr = sp._synth_piper(text)
        live = sp.pcm16(sp._resample_to_16k(audio, sr))
        pcm, fphones = entries[text]
        assert len(live) == len(pcm), text
        assert [p for p, _, _ in phones] == [p for p, _, _ in fphones]
        assert np.allclose([s for _, s, _ in phones], [s for _, s, _ in fphones], atol=1e-3)
        d = np.abs(live.astype(np.int32) - pcm.astype(np.int32))
        assert d.max() <= 2 and (d == 0).mean() >= 0.97, (text, d.max(), (d == 0).mean())


def test_a_build_writes_the_shipped_samples(tmp_path):
    from lmgs_eval.data import bundled

    bundled.build("hopper", tmp_path, size=64, seconds=1.0, seed=0, progress=False)
    with wave.open(str(tmp_path / "aud.wav")) as w:
        wav = np.frombuffer(w.readframes(w.getnframes()), "<i2")
    corpus = g.load_corpus()["train"]
    first = corpus[g.TEXT_OFFSET["hopper"] % len(corpus)]
    pcm, _ = sp.decode_frozen(sp.FROZEN_PATH.read_bytes())[1][first]
    lead = int(round(0.3 * sp.SAMPLE_RATE))
    assert not wav[:lead].any()
    n = len(wav) - lead
    assert n > 8000 and np.array_equal(wav[lead:], pcm[:n])
    # a build whose first sentence is not the shipped samples (made on an AVX-512 CPU before
    # they were shipped) is found, so ensure_bundled rebuilds it
    assert bundled.speech_is_shipped(tmp_path)
    with wave.open(str(tmp_path / "aud.wav")) as w:
        params, frames = w.getparams(), bytearray(w.readframes(w.getnframes()))
    k = 2 * (lead + 1000)
    frames[k : k + 2] = (int.from_bytes(frames[k : k + 2], "little", signed=True) + 1).to_bytes(2, "little", signed=True)
    with wave.open(str(tmp_path / "aud.wav"), "wb") as w:
        w.setparams(params)
        w.writeframes(bytes(frames))
    assert not bundled.speech_is_shipped(tmp_path)
