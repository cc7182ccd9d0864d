"""Writing a bundled subject: speech -> articulation -> rendered frames -> the processed layout."""

from __future__ import annotations

import functools
import shutil
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lmgs_eval.data.audio import write_wav
from lmgs_eval.data.bundled import articulation as art_mod
from lmgs_eval.data.bundled import speech as sp_mod
from lmgs_eval.data.bundled.head import HeadModel
from lmgs_eval.data.bundled.motion import Motion
from lmgs_eval.data.bundled.photo import PHOTOS, check_hair
from lmgs_eval.data.images import encode_png, to_u8, write_depth, write_normal, write_png, write_rgb
from lmgs_eval.data.layout_writer import (file_hashes, transforms, write_au_csv, write_json, write_lms, write_track_params,
                                          write_transforms)
from lmgs_eval.data.video import write_video
from lmgs_eval.errors import UserError

GENERATOR_VERSION = "2"  # 2: the head composited over the written plate, not the photo
FPS = 25
SPF = sp_mod.SAMPLE_RATE // FPS  # 640 samples per frame
DEPTH_SCALE = 10000.0  # depth PNG value = camera z (metres) x 10000 (0.1 mm steps, up to 6.5 m)
TRAIN_VOICE = sp_mod.PIPER_VOICE
CROSS = {  # held-out voices and texts of the cross-driven clips
    "astronaut": {"A": ("espeak:en-us+f4", "cross-a"), "B": (sp_mod.PIPER_VOICE, "cross-b")},
    "hopper": {"A": ("espeak:en-gb-x-rp+f4", "cross-a"), "B": (sp_mod.PIPER_VOICE, "cross-b")},
}
TEXT_OFFSET = {"astronaut": 0, "hopper": 24}
STANDIN = ("This is a synthetic stand-in subject made by the lmgs generator from a public-domain photograph "
           "and text-to-speech audio; it is not the paper's data (Obama, May, Lieu) and numbers on it are not "
           "comparable with published results.")
PARSING_COLOURS = {"background": (255, 255, 255), "head": (255, 0, 0), "neck": (0, 255, 0), "torso": (0, 0, 255)}
AU_COLUMNS = ("AU01_r", "AU02_r", "AU04_r", "AU05_r", "AU06_r", "AU07_r", "AU09_r", "AU10_r", "AU12_r", "AU14_r",
              "AU15_r", "AU17_r", "AU20_r", "AU23_r", "AU25_r", "AU26_r", "AU45_r")


@functools.lru_cache(maxsize=1)
def load_corpus() -> dict[str, list[str]]:
    """The committed text corpus by section (``train``, ``cross-a``, ``cross-b``)."""
    return read_sections(Path(__file__).with_name("corpus.txt"))


def read_sections(path: Path) -> dict[str, list[str]]:
    """A text corpus file by ``[section]``: one sentence a line; blank lines and ``#`` comments skipped."""
    out: dict[str, list[str]] = {}
    sec = None
    for line in path.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("[") and line.endswith("]"):
            sec = line[1:-1]
            out[sec] = []
        elif sec is None:
            raise UserError(f"{path}: text before the first [section]")
        else:
            out[sec].append(line)
    return out


def _rng(seed: int, name: str, stream: str) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(name.encode()), zlib.crc32(stream.encode())])


@functools.lru_cache(maxsize=4)
def head_model(name: str, size: int, hair: str = "layer") -> HeadModel:
    return HeadModel(name, size, hair)


@dataclass
class Clip:
    """A rendered talking clip (ground truth for every frame).

    Attributes:
        frames: uint8 ``[T, H, W, 3]``.
        audio: float32 ``[T * 640]`` at 16 kHz.
        lms2d: ``[T, 68, 2]`` pixels; lms3d: ``[T, 68, 3]`` world.
        c2w: ``[T, 4, 4]`` OpenGL camera-to-world; focal: pixels (the head model's; the
            clip's mean under a zoom).
        phonemes: the timeline (dicts with phoneme, start, end, viseme).
        articulation: ``[T, K]`` (``articulation.COLUMNS``), the head's turn included.
        text, voice: what was spoken, by whom.
        focals: ``[T]`` the focal length of every frame (pixels): ``focal`` throughout
            unless the camera zooms.
        motion: the extra motion (:class:`motion.Motion`), or None.
    """

    frames: np.ndarray
    audio: np.ndarray
    lms2d: np.ndarray
    lms3d: np.ndarray
    c2w: np.ndarray
    focal: float
    phonemes: list[dict]
    articulation: np.ndarray
    text: str
    voice: str
    focals: np.ndarray | None = None
    motion: Motion | None = None


def _check(name: str, size: int, seed: int) -> None:
    if name not in PHOTOS:
        raise UserError(f"bundled subject {name!r}: unknown (known: {', '.join(PHOTOS)})")
    if not (32 <= int(size) <= 2048):
        raise UserError(f"size {size}: must be between 32 and 2048 pixels")
    if int(seed) < 0:
        raise UserError(f"seed {seed}: must be >= 0")


def _speech_frames(speech: sp_mod.Speech, n: int) -> sp_mod.Speech:
    return sp_mod.fit_length(speech, n * SPF)


def synthesize_clip(name: str, text: str, voice: str, *, size: int, seed: int, motion: Motion | str | None = None) -> Clip:
    """Render ``name`` speaking ``text`` in ``voice`` (frames, audio and ground truth), no files.

    The clip lasts as long as the speech (plus 0.3 s lead and a short tail), rounded to frames.
    ``motion``: ``"turn"``, ``"zoom"`` or a :class:`Motion` (see ``motion.py``); the truth
    (``c2w``, ``focals``) follows it.
    """
    _check(name, size, seed)
    speech = sp_mod.synthesize([text], voice)
    n = max(1, int(np.ceil(speech.seconds * FPS)))
    return _render_clip(name, size, _speech_frames(speech, n), _rng(seed, name, f"clip:{voice}:{text}"), text, progress=None,
                        motion=Motion.of(motion))


def _render_clip(name: str, size: int, speech: sp_mod.Speech, rng: np.random.Generator, text: str, progress,
                 motion: Motion | None = None, hair: str = "layer") -> Clip:
    n = len(speech.audio) // SPF
    head = head_model(name, size, hair)
    art = art_mod.articulation(speech.phones, n, FPS, rng)
    focals = None
    if motion is not None:
        art = motion.apply(art, FPS)
        focals = motion.focals(n, FPS, head.focal)
    frames = np.zeros((n, size, size, 3), np.uint8)
    lms2d = np.zeros((n, 68, 2))
    lms3d = np.zeros((n, 68, 3))
    c2w = np.zeros((n, 4, 4))
    for i in range(n):
        fr = head.render(art[i], geometry=False, focal=None if focals is None else focals[i])
        frames[i] = to_u8(fr.rgb)
        lms2d[i], lms3d[i], c2w[i] = fr.lms2d, fr.lms3d, head.c2w(art[i])
        if progress is not None:
            progress.update(1)
    focal = head.focal if focals is None else float(focals.mean())
    return Clip(frames, speech.audio, lms2d, lms3d, c2w, focal, [p.to_json() for p in speech.phones], art, text, speech.voice,
                np.full(n, focal) if focals is None else focals, motion)


def list_voices() -> list[str]:
    """Voices available here: ``"piper:joe"`` and ``"espeak:<voice>"``."""
    return sp_mod.list_voices()


# ----------------------------------------------------------------------------- files
def _track_params(path: Path, art: np.ndarray, head: HeadModel, focal: float | None = None) -> None:
    cols = art_mod.COLUMNS
    euler = np.deg2rad(art[:, [cols.index("pitch"), cols.index("yaw"), cols.index("roll")]]).astype(np.float32)
    trans = np.stack([head.head_pose(a)[:3, 3] - [0.0, 0.0, head.D] for a in art]).astype(np.float32)
    write_track_params(path, euler, trans, head.focal if focal is None else focal)


# x264 as the subjects' mp4 is encoded on every host. Left to itself it runs as many slice threads
# as the host has CPUs (up to one per 4 macroblock rows), and every slice count is another
# bitstream; and it picks its kernels by the CPU, some of which (the AVX-512 ones among them)
# compute its macroblock-tree costs in floating point with other roundings. Two slice threads and
# the kernels up to SSE4.2 are what a 2-CPU AVX2 host gave (checked equal on the default builds).
X264_THREADS = 2
X264_ASM = "MMX2,SSE,SSE2,SSE3,SSSE3,SSE4.1,SSE4.2"


def _write_video(path: Path, frames: np.ndarray, audio: np.ndarray) -> None:
    """The subject's raw video: :func:`lmgs_eval.data.video.write_video`'s H.264 (CRF 18, veryfast,
    4:2:0) and AAC, with the encoder's threads and kernels fixed (above), so the bytes do not
    depend on the host (a change is a new :data:`GENERATOR_VERSION`)."""
    write_video(path, frames, FPS, audio if len(audio) else None, sp_mod.SAMPLE_RATE,
                threads=X264_THREADS, x264_params=f"asm={X264_ASM}")


def _cross_seconds(seconds: float) -> float:
    return float(min(9.0, max(2.0, seconds / 6.5)))


def build(name: str, out_dir: Path, *, size: int = 256, seconds: float = 60.0, seed: int = 0, progress: bool = True,
          motion: Motion | str | None = None, hair: str = "layer") -> dict:
    """Write bundled subject ``name`` into ``out_dir`` (an empty, existing folder).

    ``motion``: ``"turn"``, ``"zoom"`` or a :class:`Motion` for the training clip (the cross
    clips keep the speech motion and the fixed camera). A zoom's focal length per frame is in
    ``focal_per_frame.npy`` (the transforms files, whose layout has one ``focal_len``, carry its
    mean) and the frames' torso, parsing and background zoom with it; ``bc.jpg`` stays the
    background at the mean focal. Without ``motion`` the files are those of earlier versions,
    byte for byte.

    ``hair``: ``"layer"`` (default: the bundled subjects) or ``"head"``, where all the hair moves
    with the head as on a camera, and the subject's parsing labels it head
    (:func:`lmgs_eval.data.bundled.photo.portrait`). Recorded in ``meta.json`` when not the default.

    Returns:
        the ``meta.json`` content.
    """
    _check(name, size, seed)
    check_hair(hair)  # before the folder's checks
    motion = Motion.of(motion)
    if not (0.5 <= float(seconds) <= 3600):
        raise UserError(f"seconds {seconds:g}: must be between 0.5 and 3600")
    out = Path(out_dir)
    if not out.is_dir():
        raise UserError(f"{out}: output folder does not exist")
    if any(out.iterdir()):
        raise UserError(f"{out}: output folder is not empty")
    n = int(round(seconds * FPS))
    corpus = load_corpus()
    train = corpus["train"]
    off = TEXT_OFFSET[name] % len(train)
    train = train[off:] + train[:off]
    speech, used = sp_mod.speak_for(train, TRAIN_VOICE, n / FPS)
    speech = _speech_frames(speech, n)
    cross_n = int(round(_cross_seconds(seconds) * FPS))
    cross_speech = {}
    for key, (voice, sec) in CROSS[name].items():
        s, u = sp_mod.speak_for(corpus[sec], voice, cross_n / FPS)
        cross_speech[key] = (_speech_frames(s, cross_n), u)

    head = head_model(name, size, hair)
    art = art_mod.articulation(speech.phones, n, FPS, _rng(seed, name, "train"))
    focals = None
    if motion is not None:
        art = motion.apply(art, FPS)
        focals = motion.focals(n, FPS, head.focal)
    layers = head.static_layers()
    for d in ("ori_imgs", "gt_imgs", "torso_imgs", "parsing", "teeth_mask", "depth", "normal"):
        (out / d).mkdir()
    write_rgb(out / "bc.jpg", layers["bc"])
    torso_rgba = np.concatenate([layers["torso"], layers["torso_alpha"][:, :, None]], 2)
    torso_png = encode_png(to_u8(torso_rgba))
    torso_mask = layers["torso_alpha"] >= 0.5
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n + 2 * cross_n, desc=f"bundled {name} {size}px", unit="frame")
    frames = np.zeros((n, size, size, 3), np.uint8)
    lms2d = np.zeros((n, 68, 2))
    lms3d = np.zeros((n, 68, 3), np.float32)
    c2w = np.zeros((n, 4, 4))
    gaps = np.zeros(n)
    for i in range(n):
        if focals is None:
            fr = head.render(art[i])
        else:  # the torso and the background zoom with the head
            fr = head.render(art[i], focal=focals[i])
            layers = head.static_layers(focals[i] / head.focal)
            torso_rgba = np.concatenate([layers["torso"], layers["torso_alpha"][:, :, None]], 2)
            torso_png = encode_png(to_u8(torso_rgba))
            torso_mask = layers["torso_alpha"] >= 0.5
        frames[i] = to_u8(fr.rgb)
        lms2d[i], lms3d[i], c2w[i], gaps[i] = fr.lms2d, fr.lms3d, head.c2w(art[i]), fr.lip_gap
        write_rgb(out / "ori_imgs" / f"{i}.jpg", frames[i])
        shutil.copyfile(out / "ori_imgs" / f"{i}.jpg", out / "gt_imgs" / f"{i}.jpg")
        write_lms(out / "ori_imgs" / f"{i}.lms", lms2d[i])
        (out / "torso_imgs" / f"{i}.png").write_bytes(torso_png)
        headm = fr.head_alpha >= 0.5
        parsing = np.full((size, size, 3), 255, np.uint8)
        parsing[torso_mask & ~headm] = PARSING_COLOURS["torso"]
        parsing[layers["neck"] & ~headm] = PARSING_COLOURS["neck"]
        parsing[headm] = PARSING_COLOURS["head"]
        write_png(out / "parsing" / f"{i}.png", parsing)
        np.save(out / "teeth_mask" / f"{i}.npy", fr.mouth)
        write_depth(out / "depth" / f"{i}.png", fr.depth, DEPTH_SCALE)
        write_normal(out / "normal" / f"{i}.png", fr.normal)
        if bar is not None:
            bar.update(1)

    write_wav(out / "aud.wav", speech.audio)
    _write_video(out / f"{name}.mp4", frames, speech.audio)
    focal = head.focal if focals is None else float(focals.mean())
    write_transforms(out, c2w, focal, size, size)
    if focals is not None:
        np.save(out / "focal_per_frame.npy", focals)
    np.save(out / "lms3d.npy", lms3d)
    np.save(out / "articulation.npy", art)
    gap_norm = np.clip(gaps / 0.012, 0, 1)
    write_au_csv(out / "au.csv", art_mod.action_units(art, gap_norm), np.ones(n, bool), AU_COLUMNS)
    _track_params(out / "track_params.pt", art, head, None if focals is None else focal)
    write_json(out / "phonemes.json", [p.to_json() for p in speech.phones])
    (out / "text.txt").write_text("\n".join(used) + "\n", encoding="utf-8")

    cross_meta = {}
    for key, (cs, cu) in cross_speech.items():
        d = out / "cross" / key
        (d / "gt_imgs").mkdir(parents=True)
        (d / "ori_imgs").mkdir()
        clip = _render_clip(name, size, cs, _rng(seed, name, f"cross-{key}"), " ".join(cu), bar, hair=hair)
        for i in range(len(clip.frames)):
            write_rgb(d / "gt_imgs" / f"{i}.jpg", clip.frames[i])
            write_lms(d / "ori_imgs" / f"{i}.lms", clip.lms2d[i])
        write_wav(d / "aud.wav", clip.audio)
        np.save(d / "lms3d.npy", clip.lms3d.astype(np.float32))
        np.save(d / "articulation.npy", clip.articulation)
        write_json(d / "transforms.json", transforms(clip.c2w, range(len(clip.frames)), head.focal, size, size))
        write_json(d / "phonemes.json", clip.phonemes)
        (d / "text.txt").write_text("\n".join(cu) + "\n", encoding="utf-8")
        cross_meta[key] = {"voice": cs.voice, "frames": len(clip.frames), "seconds": len(clip.frames) / FPS, "texts": cu}
    if bar is not None:
        bar.close()

    spec = PHOTOS[name]
    meta = {
        "generator": "lmgs_eval.data.bundled",
        "generator_version": GENERATOR_VERSION,
        "bundled": True,
        "name": name,
        "standin": STANDIN,
        "seed": int(seed),
        "size": int(size),
        "seconds": float(seconds),
        "fps": FPS,
        "frames": n,
        "sample_rate": sp_mod.SAMPLE_RATE,
        "photo": spec.source,
        "photo_package": spec.package,
        "voices": {"train": TRAIN_VOICE, **{f"cross_{k}": v["voice"] for k, v in cross_meta.items()}},
        "texts": {"train": used, **{f"cross_{k}": v["texts"] for k, v in cross_meta.items()}},
        "cross": cross_meta,
        "depth_scale": DEPTH_SCALE,
        "depth": "camera z of the head surface (world units, metres) x depth_scale; 0 on torso and background",
        "normal": "camera-space unit normals of the head surface, OpenCV axes (x right, y down, z forward), facing the camera; 0 elsewhere",
        "articulation_columns": list(art_mod.COLUMNS),
        "articulation_units": "jaw, lip_*, blink, brow in [0, 1] (lip_width in [-1, 1]); yaw/pitch/roll in degrees; tx/ty/tz in metres",
        "track_params": "euler = (pitch, yaw, roll) of the head in radians; trans = head translation in the canonical camera frame (OpenGL axes, metres); focal in pixels",
        "au_csv": "OpenFace-style intensities derived from the articulation: AU45_r = 5 x eyelid closure, AU26_r = 5 x jaw opening, AU25_r from the inner-lip gap",
        "world_units": "metres; the head is fixed, the camera moves (ER-NeRF convention)",
        "teeth_mask": "visible inside-mouth surfaces (teeth, tongue, cavity)",
        "parsing_colours": {k: list(v) for k, v in PARSING_COLOURS.items()},
    }
    if hair != "layer":
        meta["hair"] = {"mode": hair, "note": "all the hair above the jaw's lower half moves with the head and is labelled head"}
    if motion is not None:
        meta["motion"] = {**motion.to_json(), "applies_to": "the training clip (ori_imgs, transforms_*.json); not the cross clips"}
        if focals is not None:
            meta["focal_per_frame"] = ("focal_per_frame.npy: the focal length of every frame in pixels; transforms_*.json carry its "
                                       "mean, bc.jpg the background at that mean; the frames' torso and background zoom with it")
    write_json(out / "meta.json", meta)
    write_json(out / "manifest.json", file_hashes(out))
    return meta


def speech_is_shipped(folder: Path) -> bool:
    """False if ``folder`` (a bundled build) speaks its first training sentence otherwise than
    the shipped piper samples say: a build made before they were shipped, on a CPU whose
    ONNX kernels gave other samples. True when there is nothing to compare."""
    import wave

    folder = Path(folder)
    try:
        first = (folder / "text.txt").read_text(encoding="utf-8").splitlines()[0].strip()
    except (OSError, IndexError):
        return True
    shipped = sp_mod.frozen_piper().get(first)
    if shipped is None or not (folder / "aud.wav").is_file():
        return True
    lead = int(round(0.3 * sp_mod.SAMPLE_RATE))  # speak_for's lead
    want = sp_mod.pcm16(shipped[0])
    try:
        with wave.open(str(folder / "aud.wav")) as w:
            got = np.frombuffer(w.readframes(lead + len(want)), "<i2")[lead:]
    except (OSError, EOFError, wave.Error):
        return False
    return np.array_equal(got, want[: len(got)])
