"""Bad input to ``lmgs-eval ingest`` as a user gives it: exit code 2, one line naming the file or flag,
nothing written (no data root made, no half-written subject)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from conftest import run_cli, write_pcm_wav
from test_bad_inputs import world  # noqa: F401  (a results store and the cache, both to stay unchanged)


def _short_clip(truth: Path, out: Path, n: int, seconds: float | None = None) -> Path:
    """The first ``n`` frames of the bundled truth as a video with ``seconds`` of its audio (default: as long)."""
    from lmgs_eval.data.audio import load_audio
    from lmgs_eval.data.images import read_rgb_u8
    from lmgs_eval.data.video import write_video

    frames = np.stack([read_rgb_u8(truth / "ori_imgs" / f"{i}.jpg") for i in range(n)])
    audio, _ = load_audio(truth / "aud.wav")
    write_video(out, frames, 25, audio[: int((n / 25 if seconds is None else seconds) * 16000)])
    return out


def test_ingest_data_root_that_cannot_be_made_and_a_name_too_long(truth, world, monkeypatch):
    from conftest import ingest_error_line

    tmp, res, snap = world
    f = tmp / "afile"
    f.write_text("keep me")
    video = truth / "astronaut.mp4"
    before = snap()
    rc, out, err = run_cli("ingest", str(video), "--data-root", str(f / "R"), "--quiet")
    ingest_error_line(rc, err, f"--data-root {f / 'R'}", f"cannot create the folder ({f} is not a folder)")
    # a folder this user may not write (root writes anywhere: refused as the OS would report it)
    ro = tmp / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == ro else real(p, mode))
    for root, words in ((ro, "folder is not writable"), (ro / "data", f"cannot create the folder ({ro} is not writable)")):
        rc, out, err = run_cli("ingest", str(video), "--data-root", str(root), "--quiet")
        ingest_error_line(rc, err, f"--data-root {root}", words)
    monkeypatch.undo()
    rc, out, err = run_cli("ingest", str(video), "--data-root", str(tmp / "data"), "--name", "a" * 300, "--quiet")
    ingest_error_line(rc, err, "--name aaaa", "300 bytes long", "at most")
    assert f.read_text() == "keep me" and list(ro.iterdir()) == [] and not (tmp / "data").exists()
    assert snap() == before


def test_ingest_refuses_an_empty_name_and_a_folder_given_as_a_file(truth, tmp_path):
    from conftest import ingest_error_line

    root = tmp_path / "data"
    rc, _, err = run_cli("ingest", str(truth / "astronaut.mp4"), "--name", "", "--data-root", str(root), "--quiet")
    ingest_error_line(rc, err, "--name ''", "plain folder name")
    rc, _, err = run_cli("ingest", str(truth), "--data-root", str(root), "--quiet")
    ingest_error_line(rc, err, str(truth), "is a folder, not a video file")
    rc, _, err = run_cli("ingest", str(truth / "astronaut.mp4"), "--audio", str(truth), "--data-root", str(root), "--quiet")
    ingest_error_line(rc, err, str(truth), "is a folder, not an audio file")
    rc, _, err = run_cli("ingest", str(tmp_path / "none.mp4"), "--data-root", str(root), "--quiet")
    ingest_error_line(rc, err, "none.mp4", "video not found")
    for bad in ("often", "-2"):
        rc, _, err = run_cli("ingest", str(truth / "astronaut.mp4"), "--pose-smooth", bad, "--data-root", str(root), "--quiet")
        ingest_error_line(rc, err, f"--pose-smooth '{bad}'", "auto or a number of frames")
    assert not root.exists()


def test_ingest_refuses_too_few_frames_or_too_little_audio(truth, tmp_path):
    from conftest import ingest_error_line
    from lmgs_eval.data.ingest.checks import MIN_FRAMES

    root = tmp_path / "data"
    one = _short_clip(truth, tmp_path / "one.mp4", 1, seconds=2.0)  # one frame, 2 s of audio
    rc, _, err = run_cli("ingest", str(one), "--data-root", str(root), "--quiet")
    ingest_error_line(rc, err, "one.mp4", "1 frame at 25 fps", "too few to make a subject", f"at least {MIN_FRAMES} frames")
    two = _short_clip(truth, tmp_path / "two.mp4", 50)
    short = tmp_path / "short.wav"
    write_pcm_wav(short, 0.2 * np.sin(np.arange(1600) / 5), 16000)  # 0.1 s
    rc, _, err = run_cli("ingest", str(two), "--audio", str(short), "--data-root", str(root), "--quiet")
    ingest_error_line(rc, err, "short.wav", "the audio is too short (0.10 s)", "the video has 2.00 s")
    assert not root.exists()  # not even an empty data root


def test_ingest_a_bad_video_makes_no_data_root(tmp_path):
    from conftest import ingest_error_line

    bad = tmp_path / "broken.mp4"
    bad.write_bytes(np.random.default_rng(0).bytes(5000))
    root = tmp_path / "a" / "b" / "data"
    rc, _, err = run_cli("ingest", str(bad), "--data-root", str(root), "--quiet")
    ingest_error_line(rc, err, "broken.mp4", "not a readable video")
    assert list(tmp_path.iterdir()) == [bad]


def _remux(src: Path, out: Path, interleave: bool) -> bytes:
    """``src`` rewritten with its index at the front (``faststart``), its packets in time order when
    ``interleave``; the bytes written."""
    import av

    with av.open(str(src)) as i:
        pk = [(float(p.dts * p.time_base), p.stream.index, p) for p in i.demux() if p.dts is not None]
        if interleave:
            pk.sort(key=lambda x: (x[0], x[1]))
        with av.open(str(out), "w", format="mp4", options={"movflags": "faststart"}) as o:
            m = {s.index: o.add_stream_from_template(s) for s in i.streams}
            for _, idx, p in pk:
                p.stream = m[idx]
                o.mux(p)
    data = out.read_bytes()
    assert data.find(b"moov") < data.find(b"mdat")  # the index before the data: a cut file still opens
    return data


def test_a_truncated_video_is_refused_or_flagged(truth, tmp_path):
    from conftest import TRUTH_SECONDS, ingest_error_line
    from lmgs_eval.data.ingest import decode
    from lmgs_eval.data.ingest.checks import check_decoded

    data = _remux(truth / "astronaut.mp4", tmp_path / "whole.mp4", interleave=True)
    assert check_decoded(decode.probe(tmp_path / "whole.mp4")) is None
    half = tmp_path / "half.mp4"
    half.write_bytes(data[: len(data) // 2])
    root = tmp_path / "data"
    rc, _, err = run_cli("ingest", str(half), "--data-root", str(root), "--quiet")
    ingest_error_line(rc, err, "half.mp4", "the file is cut short", f"of the {TRUTH_SECONDS:.2f} s of video", "missing")
    assert not root.exists()
    # a little missing: made from what decodes, with a warning (flagged in the manifest)
    tail = tmp_path / "tail.mp4"
    tail.write_bytes(data[: int(len(data) * 0.97)])
    info = decode.probe(tail)
    assert 0 < info.missing_seconds < 0.1 * info.stated_duration
    warning = check_decoded(info)
    assert warning.startswith(f"{tail}: the file is cut short: the last ") and "the subject is made from what decodes" in warning


# ----------------------------------------------------------------------------- subjects, protocols


def test_a_missing_or_altered_shipped_model_stops_the_ingest_before_anything_is_written(truth, tmp_path, monkeypatch):
    """The ingest's model files are checked first: a missing one, or one whose bytes differ from those
    shipped, is one line naming the file, exit 2, and no data root."""
    import shutil

    from conftest import ingest_error_line
    from lmgs_eval.data.ingest import vendored

    models = tmp_path / "models"
    shutil.copytree(vendored.FOLDER, models)
    monkeypatch.setattr(vendored, "FOLDER", models)
    root = tmp_path / "data"
    for name in vendored.MODELS:
        f = models / name
        keep = f.read_bytes()
        f.unlink()
        rc, out, err = run_cli("ingest", str(truth / "astronaut.mp4"), "--data-root", str(root), "--quiet")
        ingest_error_line(rc, err, str(f), "is missing")
        f.write_bytes(keep[:-1] + bytes([keep[-1] ^ 1]))
        rc, out, err = run_cli("ingest", str(truth / "astronaut.mp4"), "--data-root", str(root), "--quiet")
        ingest_error_line(rc, err, str(f), "is altered")
        f.write_bytes(keep)
        assert not root.exists()
