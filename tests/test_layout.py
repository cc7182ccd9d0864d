"""The ER-NeRF/TalkingGaussian layout reader on a hand-made folder, and its bad inputs."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from conftest import make_ernerf_folder, run_cli, write_pcm_wav
from lmgs_eval.data.layout import read_subject, split_point
from lmgs_eval.errors import UserError


def test_reads_what_was_written(ernerf_folder):
    root, w = ernerf_folder
    s = read_subject(root)
    assert s.n_frames == w["n"] and (s.width, s.height) == (w["size"], w["size"])
    np.testing.assert_allclose(s.c2w, w["c2w"], atol=1e-6)
    np.testing.assert_allclose(s.landmarks, w["lms"], atol=1e-4)
    np.testing.assert_allclose(s.blink, w["blink"], atol=1e-6)
    assert s.aus["AU25_r"].shape == (w["n"],)
    assert s.audio.shape == (w["n"] * 640,)
    np.testing.assert_allclose(s.audio, w["audio"], atol=1.0 / 32767)
    assert s.audio_features["ds"].shape == (w["n"], 16, 29)
    assert s.focal == 40.0 and s.cx == w["size"] / 2
    assert read_subject(root, derive=False).notes == ()  # nothing repaired
    assert len(s.notes) == 1 and "derived" in s.notes[0]  # 3D landmarks and a head prior, named
    assert s.frame(3).shape == (w["size"], w["size"], 3)
    assert s.frame(3).dtype == np.uint8 and abs(float(s.frame(3).mean()) - (40 + 30)) < 2


@pytest.mark.parametrize("n,expected", [(11, 10), (12, 10), (22, 20), (450, 409), (5500, 5000), (1, 0)])
def test_split_is_first_ten_elevenths(n, expected):
    assert split_point(n) == expected


def test_split_from_transforms(ernerf_folder):
    root, w = ernerf_folder
    s = read_subject(root)
    assert list(s.train_ids) == list(range(w["cut"]))
    assert list(s.test_ids) == list(range(w["cut"], w["n"]))


def test_camera_convention_matches_talkinggaussian(ernerf_folder):
    """OpenGL camera-to-world (camera at z=+1 looking down -z): hand-computed projections."""
    import torch

    root, _ = ernerf_folder
    cam = read_subject(root).camera(0)  # c2w = identity moved to z = 1
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    uv = cam.project(pts)
    # x right stays right; world +y (up) goes to smaller pixel rows; depth 1.
    torch.testing.assert_close(uv, torch.tensor([[16.0, 16.0], [16.0 + 4.0, 16.0], [16.0, 16.0 - 4.0]]))
    np.testing.assert_allclose(cam.to_nerf_c2w(), np.asarray(read_subject(root).c2w[0], np.float64), atol=1e-6)


def test_stereo_44k_audio_is_repaired_with_notes(ernerf_folder):
    root, w = ernerf_folder
    t = np.arange(int(w["n"] * 0.04 * 44100) + 10) / 44100
    x = 0.25 * np.sin(2 * np.pi * 220 * t)
    write_pcm_wav(root / "aud.wav", np.stack([x, x], axis=1), 44100)
    s = read_subject(root)
    assert any("mixed to mono" in n for n in s.notes) and any("resampled from 44100" in n for n in s.notes)
    assert s.audio.shape[0] >= w["n"] * 640
    # still a 220 Hz tone: the spectrum peaks there
    spec = np.abs(np.fft.rfft(s.audio[: w["n"] * 640]))
    freqs = np.fft.rfftfreq(w["n"] * 640, 1 / 16000)
    assert abs(freqs[spec.argmax()] - 220) < 5


def _expect_error(root, *fragments):
    with pytest.raises(UserError) as ei:
        read_subject(root)
    msg = str(ei.value)
    assert "\n" not in msg
    for f in fragments:
        assert f in msg, msg
    return msg


def test_missing_transforms(ernerf_folder):
    root, _ = ernerf_folder
    (root / "transforms_val.json").unlink()
    _expect_error(root, "transforms_val.json")


def test_corrupt_transforms(ernerf_folder):
    root, _ = ernerf_folder
    (root / "transforms_train.json").write_text("{not json")
    _expect_error(root, "transforms_train.json", "not valid JSON")


def test_landmark_file_wrong_shape(ernerf_folder):
    root, _ = ernerf_folder
    np.savetxt(root / "ori_imgs" / "5.lms", np.zeros((67, 2)))
    _expect_error(root, "5.lms", "68")


def test_frame_count_does_not_match_transforms(ernerf_folder):
    root, _ = ernerf_folder
    (root / "gt_imgs" / "7.jpg").unlink()
    _expect_error(root, "gt_imgs", "7.jpg", "missing")


def test_corrupt_image(ernerf_folder):
    root, _ = ernerf_folder
    (root / "gt_imgs" / "0.jpg").write_bytes(b"not a jpeg")
    _expect_error(root, "0.jpg", "not a readable image")


def test_audio_shorter_than_frames(ernerf_folder):
    root, w = ernerf_folder
    write_pcm_wav(root / "aud.wav", np.zeros(w["n"] * 640 // 2), 16000)
    _expect_error(root, "aud.wav", "shorter than the")


def test_audio_short_by_less_than_a_frame_is_padded(ernerf_folder):
    root, w = ernerf_folder
    write_pcm_wav(root / "aud.wav", np.zeros(w["n"] * 640 - 100), 16000)
    s = read_subject(root)
    assert s.audio.shape == (w["n"] * 640,) and any("silence appended" in n for n in s.notes)


def test_empty_and_non_audio_files(ernerf_folder):
    root, _ = ernerf_folder
    (root / "aud.wav").write_bytes(b"")
    _expect_error(root, "aud.wav", "empty")
    (root / "aud.wav").write_bytes(b"RIFF garbage that is not audio" * 10)
    _expect_error(root, "aud.wav")


def test_au_csv_without_blink(ernerf_folder):
    root, _ = ernerf_folder
    (root / "au.csv").write_text("frame, AU01_r\n1, 0.0\n")
    _expect_error(root, "au.csv", "AU45_r")


def test_au_csv_missing_is_a_note(ernerf_folder):
    root, w = ernerf_folder
    (root / "au.csv").unlink()
    s = read_subject(root)
    assert np.all(s.blink == 0) and any("au.csv" in n for n in s.notes)


def test_feature_shapes(ernerf_folder):
    root, w = ernerf_folder
    np.save(root / "aud_ds.npy", np.zeros((w["n"], 16, 30), np.float32))
    _expect_error(root, "aud_ds.npy", "[N, 16, 29]")
    np.save(root / "aud_ds.npy", np.zeros((w["n"] - 1, 16, 29), np.float32))
    _expect_error(root, "aud_ds.npy", "rows for")


def test_hubert_features_reshaped(ernerf_folder):
    root, w = ernerf_folder
    (root / "aud_ds.npy").unlink()
    np.save(root / "aud.npy", np.ones((2 * w["n"], 1024), np.float32))
    s = read_subject(root)
    assert s.audio_features["hu"].shape == (w["n"], 2, 1024)
    assert any("aud.npy" in n for n in s.notes)


def test_video_not_25_fps(ernerf_folder):
    from lmgs_eval.data.video import write_video

    root, _ = ernerf_folder
    write_video(root / f"{root.name}.mp4", np.zeros((6, 32, 32, 3), np.uint8), fps=30)
    _expect_error(root, "tiny.mp4", "30 fps")


def test_img_ids_must_cover_frames(ernerf_folder):
    root, _ = ernerf_folder
    d = json.loads((root / "transforms_val.json").read_text())
    d["frames"][0]["img_id"] = 99
    (root / "transforms_val.json").write_text(json.dumps(d))
    _expect_error(root, "img_id")


# ----------------------------------------------------------------------------- CLI
def test_cli_paper_subject_missing_says_where_and_how(tmp_path):
    rc, out, err = run_cli("prepare", "--subject", "obama", "--data-root", str(tmp_path))
    assert rc == 2
    assert str(tmp_path / "obama") in err and "process.py" in err
    assert "Traceback" not in err and err.count("\n") == 1


def test_cli_unknown_subject_lists_known(tmp_path):
    make_ernerf_folder(tmp_path / "mine")
    rc, _, err = run_cli("prepare", "--subject", "nobody", "--data-root", str(tmp_path))
    assert rc == 2 and "astronaut" in err and "mine" in err


def test_cli_subject_by_path_and_by_name(tmp_path):
    make_ernerf_folder(tmp_path / "mine")
    rc, out, _ = run_cli("prepare", "--subject", str(tmp_path / "mine"))
    assert rc == 0 and "12 frames" in out and "10 train / 2 test" in out
    rc, out, _ = run_cli("subjects", "--json", "--data-root", str(tmp_path))
    rows = {r["name"]: r for r in json.loads(out)["subjects"]}
    assert rows["mine"]["frames"] == 12 and rows["mine"]["built"]
    assert rows["obama"]["built"] is False and rows["astronaut"]["bundled"] is True


def test_cli_broken_subject_is_listed_not_fatal(tmp_path):
    make_ernerf_folder(tmp_path / "broken")
    shutil.rmtree(tmp_path / "broken" / "gt_imgs")
    rc, out, _ = run_cli("subjects", "--json", "--data-root", str(tmp_path))
    rows = {r["name"]: r for r in json.loads(out)["subjects"]}
    assert rc == 0 and rows["broken"]["status"].startswith("error:")


def test_cli_prepare_reports_the_ground_truth_head_on_the_plate(tmp_path):
    import cv2

    info = make_ernerf_folder(tmp_path / "mine")
    size = info["size"]
    for i in range(info["n"]):
        p = np.full((size, size, 3), 255, np.uint8)
        p[:, : size // 2] = (0, 0, 255)  # parsing's head colour (BGR red) on the left half
        cv2.imwrite(str(tmp_path / "mine" / "parsing" / f"{i}.png"), p)
    rc, out, err = run_cli("prepare", "--subject", str(tmp_path / "mine"))
    # the left half is the frame (uniform 40 + 10 i), the right half the plate: bc.jpg (black), no torso_imgs
    want = np.mean([10 * np.log10(255**2 / ((40 + 10 * i) ** 2 / 2)) for i in range(info["cut"], info["n"])])
    assert rc == 0, err
    assert f"PSNR {want:.2f} dB" in out and "GT head on plate" in out


def test_normal_maps_round_trip_and_no_surface_reads_as_zero(tmp_path):
    from lmgs_eval.data.images import read_normal, write_normal

    rng = np.random.default_rng(0)
    n = rng.normal(size=(8, 8, 3))
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    n[:3] = 0.0  # no surface: stored as black
    write_normal(tmp_path / "n.png", n)
    back = read_normal(tmp_path / "n.png")
    assert np.all(back[:3] == 0)
    np.testing.assert_allclose(np.linalg.norm(back[3:], axis=2), 1.0, atol=1e-6)
    assert np.degrees(np.arccos(np.clip((back[3:] * n[3:]).sum(-1), -1, 1))).max() < 1.0  # 8-bit quantisation
