"""``lmgs-eval ingest`` on footage shaped as real footage comes: two faces, a face hidden for a
moment or for longer, a scene cut, a change of light, a moving camera, audio shorter than the video.
Each is made from the bundled ``truth`` subject's own frames (conftest).
"""

from __future__ import annotations

import json

import numpy as np

from conftest import TRUTH_SIZE as SIZE, entries, ingest_error_line, run_cli


def test_scene_cut_is_refused_with_its_frame(truth, tmp_path):
    from lmgs_eval.data.images import read_rgb_u8
    from lmgs_eval.data.video import write_video

    frames = np.stack([read_rgb_u8(truth / "ori_imgs" / f"{i}.jpg") for i in range(30)])
    frames[18:] = frames[18:, ::-1, ::-1] // 3  # another "shot" from frame 18
    write_video(tmp_path / "cut.mp4", frames, 25, np.zeros(30 * 640, np.float32))
    root = tmp_path / "data"
    rc, _, err = run_cli("ingest", str(tmp_path / "cut.mp4"), "--data-root", str(root), "--quiet")
    ingest_error_line(rc, err, "cut.mp4", "scene cut", "frame 18")
    assert entries(root) == []


def test_a_sudden_change_of_light_is_refused_as_such(truth, tmp_path):
    """The same picture 40 % brighter from frame 18 (a lamp switched on) is not called a scene
    cut but a change of light, with its frame; a cut to another picture still is a cut."""
    from lmgs_eval.data.images import read_rgb_u8
    from lmgs_eval.data.video import write_video
    from lmgs_eval.data.ingest import decode

    frames = np.stack([read_rgb_u8(truth / "ori_imgs" / f"{i}.jpg") for i in range(30)])
    lit = frames.copy()
    lit[18:] = np.clip(lit[18:].astype(np.float32) * 1.4, 0, 255).astype(np.uint8)
    thumbs = lambda x: np.stack([f.mean(-1)[::4, ::4] / 255.0 for f in x])  # noqa: E731
    assert decode.scene_cuts(thumbs(lit)) == [18] and decode.light_jumps(thumbs(lit), [18]) == [18]
    cut = frames.copy()
    cut[18:] = cut[18:, ::-1, ::-1] // 3
    assert decode.scene_cuts(thumbs(cut)) == [18] and decode.light_jumps(thumbs(cut), [18]) == []
    write_video(tmp_path / "lamp.mp4", lit, 25, np.zeros(30 * 640, np.float32))
    root = tmp_path / "data"
    rc, _, err = run_cli("ingest", str(tmp_path / "lamp.mp4"), "--data-root", str(root), "--quiet")
    ingest_error_line(rc, err, "lamp.mp4", "the light changes at once", "frame 18")
    assert "scene cut" not in err and entries(root) == []


def test_two_faces_track_the_central_one_and_say_so(truth, tmp_path):
    from lmgs_eval.data.audio import load_audio
    from lmgs_eval.data.images import read_rgb_u8
    from lmgs_eval.data.video import write_video

    frames = []
    for i in range(25):
        face = read_rgb_u8(truth / "ori_imgs" / f"{i}.jpg")
        pad = np.full((SIZE, 64, 3), 128, np.uint8)
        # two faces of one size; the right-hand one is nearer the frame's centre
        frames.append(np.concatenate([face[:, ::-1], face, pad], axis=1))
    audio, _ = load_audio(truth / "aud.wav")
    write_video(tmp_path / "two.mp4", np.stack(frames), 25, audio[: 25 * 640])
    root = tmp_path / "data"
    rc, out, err = run_cli("ingest", str(tmp_path / "two.mp4"), "--size", "128", "--data-root", str(root), "--quiet")
    assert rc == 0, err
    man = json.loads((root / "two" / "manifest.json").read_text())
    assert "2 faces" in man["flags"]["several_faces"]
    assert man["window"]["x0"] >= SIZE * 0.9  # the window is on the right-hand face


def test_a_briefly_hidden_face_is_not_swapped_for_another(truth, tmp_path):
    """The tracked face is hidden for three frames at a re-detection frame while another face
    stays in view: the hidden frames are interpolated and the track stays on its face (taking
    the other one there would carry the track, the crop and every later frame to it)."""
    from lmgs_eval.data.audio import load_audio
    from lmgs_eval.data.images import read_rgb_u8
    from lmgs_eval.data.video import write_video
    from lmgs_eval.data.ingest.track import REDETECT

    n, hidden = 2 * REDETECT, range(REDETECT, REDETECT + 3)
    frames = []
    for i in range(n):
        face = read_rgb_u8(truth / "ori_imgs" / f"{i}.jpg")
        pad = np.full((SIZE, 64, 3), 128, np.uint8)
        mine = np.full_like(face, 128) if i in hidden else face
        # the right-hand face is nearer the frame's centre: it is the one tracked
        frames.append(np.concatenate([face[:, ::-1], mine, pad], axis=1))
    audio, _ = load_audio(truth / "aud.wav")
    write_video(tmp_path / "hide.mp4", np.stack(frames), 25, audio[: n * 640])
    root = tmp_path / "data"
    rc, out, err = run_cli("ingest", str(tmp_path / "hide.mp4"), "--size", "128", "--data-root", str(root), "--quiet")
    assert rc == 0, err
    man = json.loads((root / "hide" / "manifest.json").read_text())
    assert man["window"]["x0"] >= SIZE * 0.9  # the window is still on the right-hand face
    assert f"frames {hidden[0]}-{hidden[-1]}" in man["flags"]["interpolated"]
    assert "other than the tracked one" in man["flags"]["several_faces"] and f"{hidden[0]}-" in man["flags"]["several_faces"]


def test_a_long_faceless_stretch_is_left_out_with_its_audio(truth, tmp_path):
    """The face hidden for 20 frames (longer than interpolation bridges) in the middle: those
    frames and their audio are left out, listed, and the frames after them follow on."""
    from conftest import write_pcm_wav
    from lmgs_eval.data.audio import load_audio
    from lmgs_eval.data.images import read_rgb_u8
    from lmgs_eval.data.video import write_video
    from lmgs_eval.data.ingest.track import MAX_GAP
    from lmgs_eval.data.layout import read_subject

    n, hidden = 60, range(20, 40)
    assert len(hidden) > MAX_GAP
    truth_frames = [read_rgb_u8(truth / "ori_imgs" / f"{i}.jpg") for i in range(n)]
    frames = []
    for i, f in enumerate(truth_frames):
        if i in hidden:  # a hand before the face: its landmarks' box, filled with skin colour
            lm = np.loadtxt(truth / "ori_imgs" / f"{i}.lms")
            (x0, y0), (x1, y1) = lm.min(0).astype(int) - 4, lm.max(0).astype(int) + 4
            f = f.copy()
            f[max(y0, 0) : y1, max(x0, 0) : x1] = (200, 150, 120)
        frames.append(f)
    audio, _ = load_audio(truth / "aud.wav")
    write_video(tmp_path / "away.mp4", np.stack(frames), 25, audio[: n * 640])
    write_pcm_wav(tmp_path / "away.wav", audio[: n * 640], 16000)  # given, so the samples can be compared exactly
    root = tmp_path / "data"
    rc, out, err = run_cli("ingest", str(tmp_path / "away.mp4"), "--audio", str(tmp_path / "away.wav"), "--size", str(SIZE),
                           "--data-root", str(root), "--quiet")
    assert rc == 0, err
    man = json.loads((root / "away" / "manifest.json").read_text())
    assert man["frames"]["kept"] == n - len(hidden)
    assert man["frames"]["source_runs"] == [[0, hidden[0]], [hidden[-1] + 1, n]]
    assert f"frames {hidden[0]}-{hidden[-1]}" in man["flags"]["faceless_gaps"]
    s = read_subject(root / "away")
    assert s.n_frames == n - len(hidden)
    # the audio of the kept frames, joined (two 16-bit round trips)
    kept = np.concatenate([audio[: hidden[0] * 640], audio[(hidden[-1] + 1) * 640 : n * 640]])
    np.testing.assert_allclose(s.audio, kept, atol=3 / 32767)
    # subject frame 20 is source frame 40: the frame after the gap, not the hidden one
    after = s.frame(hidden[0]) / 255.0
    assert np.abs(after - truth_frames[hidden[-1] + 1] / 255.0).mean() < 0.03
    assert np.abs(after - truth_frames[hidden[-1]] / 255.0).mean() > np.abs(after - truth_frames[hidden[-1] + 1] / 255.0).mean()


def test_moving_camera_is_flagged_with_its_frames(truth, tmp_path):
    import cv2

    from lmgs_eval.data.audio import load_audio
    from lmgs_eval.data.images import read_rgb_u8
    from lmgs_eval.data.video import write_video

    # a textured background that pans 1.5 px a frame behind the person (no cut): the plate,
    # which assumes a still camera, cannot match it
    yy, xx = np.mgrid[0:SIZE, 0 : 2 * SIZE]
    texture = np.repeat((60 + 140 * (((xx // 12) + (yy // 12)) % 2))[..., None], 3, 2).astype(np.float32)  # checks
    frames = []
    for i in range(40):
        img = read_rgb_u8(truth / "ori_imgs" / f"{i}.jpg")
        bg = np.all(read_rgb_u8(truth / "parsing" / f"{i}.png") == 255, axis=-1)
        m = np.array([[1.0, 0, -1.5 * i], [0, 1.0, 0]])
        back = cv2.warpAffine(texture, m, (SIZE, SIZE))
        frames.append(np.where(bg[..., None], np.clip(back, 0, 255).astype(np.uint8), img))
    audio, _ = load_audio(truth / "aud.wav")
    write_video(tmp_path / "pan.mp4", np.stack(frames), 25, audio[: 40 * 640])
    root = tmp_path / "data"
    rc, _, err = run_cli("ingest", str(tmp_path / "pan.mp4"), "--size", "128", "--data-root", str(root), "--quiet")
    assert rc == 0, err
    flag = json.loads((root / "pan" / "manifest.json").read_text())["flags"].get("moving_camera", "")
    assert "moving camera" in flag and "video frames 0-" in flag
    assert "moving camera" in err


def test_shorter_audio_drops_the_frames_it_does_not_cover(truth, tmp_path):
    from conftest import write_pcm_wav
    from lmgs_eval.data.audio import load_audio
    from lmgs_eval.data.layout import read_subject

    audio, _ = load_audio(truth / "aud.wav")
    write_pcm_wav(tmp_path / "short.wav", audio[: 50 * 640 + 100], 16000)  # 2 s for a 3 s video
    root = tmp_path / "data"
    rc, out, err = run_cli("ingest", str(truth / "astronaut.mp4"), "--audio", str(tmp_path / "short.wav"), "--name", "cut",
                           "--size", "128", "--data-root", str(root), "--quiet")
    assert rc == 0, err
    s = read_subject(root / "cut")
    assert s.n_frames == 50
    assert "audio_shorter" in json.loads((root / "cut" / "manifest.json").read_text())["flags"]
    # the given audio from the first frame (two 16-bit round trips, each scaling by 32767 / 32768)
    np.testing.assert_allclose(s.audio, audio[: 50 * 640], atol=3 / 32767)
