"""Bad input through the CLI as a user types it: exit code 2, one line naming the file or flag, nothing written.

Each case runs in-process on tiny inputs (a 12-frame hand-made subject, a few PNGs, a short
WAV) and checks the store and the caches are as before. The cases that need a trained model
are in test_protocols.py / test_store_lock.py, the ingest cases in test_bad_inputs_ingest.py.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from conftest import make_ernerf_folder, one_line_error, run_cli, write_pcm_wav


def tree(*roots: Path) -> dict[str, tuple[int, int]]:
    """Every file and folder under ``roots`` with its size and mtime: what a failed command must leave as it was."""
    out = {}
    for root in roots:
        if not root.exists():
            continue
        for p in sorted(root.rglob("*")):
            st = p.stat()
            # a lock file is touched by whoever takes the lock: its presence counts, not its time
            out[str(p)] = (st.st_size if p.is_file() else -1, 0 if p.name.endswith(".lock") else st.st_mtime_ns)
    return out


@pytest.fixture
def world(tmp_path):
    """A results store with one record-like file, and the test's cache root: both must not change."""
    res = tmp_path / "results"
    res.mkdir()
    cache = Path(os.environ["XDG_CACHE_HOME"])
    cache.mkdir(parents=True, exist_ok=True)
    return tmp_path, res, lambda: tree(res, cache)


def write_frames(folder: Path, numbers, size: int = 16) -> None:
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    for i in numbers:
        cv2.imwrite(str(folder / f"{i}.png"), np.full((size, size, 3), 10 * (i % 20), np.uint8))


def test_a_non_checkpoint_file_given_as_weights(world):
    tmp, res, snap = world
    wav = tmp / "some.wav"
    write_pcm_wav(wav, np.zeros(1600), 16000)
    before = snap()
    rc, out, err = run_cli("weights", "import-syncnet", str(wav))
    one_line_error(rc, out, err, str(wav), "not a readable")
    write_frames(tmp / "pred", range(3))
    rc, out, err = run_cli("score", "--pred", str(tmp / "pred"), "--gt", str(tmp / "pred"), "--alexnet", str(wav),
                           "--metrics", "lpips")
    one_line_error(rc, out, err, str(wav), "not a readable")
    assert snap() == before


def _edit_trunk(kind: str, sd: dict) -> None:
    import torch

    if kind == "shape":
        sd["features.3.weight"] = torch.zeros(192, 64, 3, 3)
    elif kind == "missing":
        del sd["features.0.weight"]
    else:  # a DataParallel-style prefix: every key renamed
        for k in [k for k in sd if k.startswith("features.")]:
            sd["module." + k] = sd.pop(k)


@pytest.mark.parametrize("kind, words", [
    ("shape", ["features.3.weight: expected shape (192, 64, 5, 5), got (192, 64, 3, 3)"]),
    ("missing", ["missing 'features.0.weight'"]),
    ("renamed", ["missing 'features.0.weight', 'features.0.bias'", "and 6 more", "unexpected 'module.features.0.bias'"]),
])
def test_an_alexnet_checkpoint_out_of_torchvisions_layout(world, kind, words):
    import torch

    from conftest import random_alexnet_state
    from lmgs_eval.metrics.lpips import lpips_heads_path

    if lpips_heads_path() is None:
        pytest.skip("lpips wheel not installed")
    tmp, res, snap = world
    ck = tmp / "alexnet-owt-7be5be79.pth"
    sd = random_alexnet_state()
    _edit_trunk(kind, sd)
    torch.save(sd, ck)
    write_frames(tmp / "pred", range(3), size=40)
    before = snap()
    rc, out, err = run_cli("score", "--pred", str(tmp / "pred"), "--gt", str(tmp / "pred"), "--alexnet", str(ck),
                           "--metrics", "lpips")
    line = one_line_error(rc, out, err, str(ck), *words)
    assert " c1." not in line and " c2." not in line  # torchvision's key, not the port's layer name
    assert len(err.strip().splitlines()) == 1, err
    assert snap() == before


@pytest.mark.parametrize("seed", ["-1", str(2 ** 32)])
def test_a_seed_out_of_range(world, seed):
    tmp, res, snap = world
    before = snap()
    rc, out, err = run_cli("self", "--subject", "astronaut-64px-2s", "--results", str(res), "--seed", seed,
                           "--no-progress")
    one_line_error(rc, out, err, f"--seed {seed}", "0 to")
    rc, out, err = run_cli("prepare", "--subject", "astronaut-64px-2s", "--seed", seed)
    one_line_error(rc, out, err, f"--seed {seed}")
    assert snap() == before


def test_table_out_is_an_existing_file_or_under_one(world):
    tmp, res, snap = world
    f = tmp / "afile"
    f.write_text("keep me")
    before = snap()
    rc, out, err = run_cli("table", "--results", str(res), "--out", str(f))
    one_line_error(rc, out, err, f"--out {f}", "not a folder")
    rc, out, err = run_cli("table", "--results", str(res), "--out", str(f / "sub"))
    one_line_error(rc, out, err, f"--out {f / 'sub'}", "cannot create")
    assert f.read_text() == "keep me" and snap() == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_table_out_read_only(world):
    tmp, res, snap = world
    ro = tmp / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        for out_dir, words in ((ro, "not writable"), (ro / "sub", "cannot create")):
            rc, out, err = run_cli("table", "--results", str(res), "--out", str(out_dir))
            one_line_error(rc, out, err, str(out_dir), words)
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o755)


def test_verify_fails_on_an_unreadable_record(world, tmp_path):
    tmp, res, snap = world
    bad = res / "lmgs" / "astronaut" / "self--0--abc.json"
    bad.parent.mkdir(parents=True)
    bad.write_text('{"schema_version": 2, "method": {"na')  # a record cut short
    (res / "notes.json").write_text('{"any": "other json"}')  # not a record: a warning only
    rc, out, err = run_cli("verify", str(res))
    assert rc == 1 and "Traceback" not in err
    assert f"error: {bad}: skipped, not readable JSON" in err
    assert "warning:" in err and "notes.json" in err
    assert "1 record files could not be read" in out and "all inputs unchanged" not in out


def test_score_metrics_unknown_name_and_reference_metric_without_gt(world):
    tmp, res, snap = world
    write_frames(tmp / "pred", range(4))
    before = snap()
    rc, out, err = run_cli("score", "--pred", str(tmp / "pred"), "--gt", str(tmp / "pred"), "--metrics", "psnr,foo")
    one_line_error(rc, out, err, "--metrics", "unknown metric foo", "known: psnr")
    rc, out, err = run_cli("score", "--pred", str(tmp / "pred"), "--metrics", "psnr")
    one_line_error(rc, out, err, "--metrics psnr", "--gt")
    assert snap() == before
    # the valid subset still scores, and only what was asked
    rc, out, err = run_cli("score", "--pred", str(tmp / "pred"), "--gt", str(tmp / "pred"), "--metrics", "psnr",
                           "--json")
    assert rc == 0, err
    assert set(json.loads(out)["results"]) == {"psnr"}


def test_a_frame_folder_with_a_numbering_gap(world):
    tmp, res, snap = world
    write_frames(tmp / "gap", [i for i in range(50) if i != 10])
    write_frames(tmp / "gt", range(50))
    for extra in ([], ["--truncate"]):
        rc, out, err = run_cli("score", "--pred", str(tmp / "gap"), "--gt", str(tmp / "gt"), "--metrics", "psnr",
                               *extra)
        one_line_error(rc, out, err, str(tmp / "gap"), "from 9 to 11", "frame 10 missing")
    # numbered the other way ER-NeRF writes them, with no gap: scored in numeric order
    write_frames(tmp / "ok", range(12))
    from lmgs_eval.data.frames import list_frames
    from lmgs_eval.errors import UserError

    assert [p.stem for p in list_frames(tmp / "ok")] == [str(i) for i in range(12)]
    (tmp / "ok" / "07.png").write_bytes((tmp / "ok" / "7.png").read_bytes())
    with pytest.raises(UserError, match="frame 7 twice"):
        list_frames(tmp / "ok")


def test_external_renders_with_a_gap(tmp_path):
    from lmgs_eval.hooks import read_frames
    from lmgs.errors import InputError

    write_frames(tmp_path / "r", [0, 1, 2, 4, 5])
    with pytest.raises(InputError, match=r"frame 3 missing"):
        read_frames(tmp_path / "r")


@pytest.mark.parametrize("damage, words", [
    (lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 64), "not a JPEG file"),
    (lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]), "cut short"),
])
def test_prepare_checks_every_frame_is_a_jpeg(tmp_path, damage, words):
    root = tmp_path / "subj"
    make_ernerf_folder(root)
    rc, out, err = run_cli("prepare", "--subject", str(root))
    assert rc == 0, err
    damage(root / "gt_imgs" / "7.jpg")
    rc, out, err = run_cli("prepare", "--subject", str(root))
    one_line_error(rc, out, err, str(root / "gt_imgs" / "7.jpg"), words)


def test_load_torch_state_on_text_and_audio(tmp_path):
    from lmgs_eval.errors import UserError
    from lmgs_eval.metrics.ort import load_torch_state

    for name, data in (("a.wav", b"RIFF\x24\x00\x00\x00WAVEfmt "), ("b.txt", b"hello\n"), ("c.pth", b"")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(UserError, match="not a readable syncnet"):
            load_torch_state(tmp_path / name, "syncnet checkpoint")


@pytest.mark.parametrize("extra, words", [
    (["--set", "train.dynamic_steps=abc"], ["train.dynamic_steps"]),
    (["--set", "nosuch.key=1"], ["nosuch.key"]),
    (["--device", "banana"], ["banana"]),
    (["--device", "cuda"], ["cuda"]),
    (["--method", "adnerf", "--preset", "paper"], ["adnerf", "paper"]),
    (["--method", "nope"], ["unknown method 'nope'"]),
    (["--subject", "nobody"], ["unknown subject"]),
])
def test_bad_run_options_stop_before_any_work(world, extra, words):
    tmp, res, snap = world
    assert run_cli("prepare", "--subject", "astronaut-64px-2s")[0] == 0  # the subject is data, built once
    before = snap()
    for cmd in ("self", "cross"):
        rc, out, err = run_cli(cmd, "--subject", "astronaut-64px-2s", "--results", str(res), "--no-progress", *extra)
        one_line_error(rc, out, err, *words)
    assert snap() == before


def test_table_out_not_writable_as_the_os_reports_it(world, monkeypatch):
    # root may write anywhere, so the refusal is driven through os.access, as a user without the right sees it
    tmp, res, snap = world
    ro = tmp / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == ro else real(p, mode))
    for out_dir, words in ((ro, "folder is not writable"), (ro / "sub", f"cannot create the folder ({ro} is not writable)")):
        rc, out, err = run_cli("table", "--results", str(res), "--out", str(out_dir))
        one_line_error(rc, out, err, f"--out {out_dir}", words)
    assert list(ro.iterdir()) == []


# ----------------------------------------------------------------------------- ingest: checked before anything is made
def test_a_one_frame_subject_is_refused_by_prepare_and_self(world):
    tmp, res, snap = world
    root = tmp / "one"
    make_ernerf_folder(root, n=1)  # what a one-frame video made: 0 train / 1 test
    before = snap()
    for cmd in (("prepare", "--subject", str(root)), ("self", "--subject", str(root), "--results", str(res), "--no-progress")):
        rc, out, err = run_cli(*cmd)
        one_line_error(rc, out, err, str(root), "1 frame, split 0 train / 1 test", "too few frames", "2 or more")
    assert snap() == before


def test_external_renders_are_checked_before_any_record(world):
    tmp, res, snap = world
    assert run_cli("prepare", "--subject", "astronaut-64px-2s")[0] == 0  # the subject is data, built once
    (tmp / "bad").mkdir()
    (tmp / "bad" / "notes.txt").write_text("no frames here")
    write_frames(tmp / "three", range(3), size=64)  # the test split has 5 frames
    before = snap()
    for renders, words in ((tmp / "bad", "folder has no images"), (tmp / "three", "3 frames, but the protocol's clip has 5")):
        rc, out, err = run_cli("self", "--subject", "astronaut-64px-2s", "--method", "external:other", "--renders",
                               str(renders), "--results", str(res), "--no-progress")
        one_line_error(rc, out, err, str(renders), words)
        assert "scoring" not in err
    assert snap() == before and list(res.iterdir()) == []


# ----------------------------------------------------------------------------- report, verify
def _records_store(root: Path) -> None:
    from lmgs_eval.results import write_record
    from test_results import fixture_records

    for r in fixture_records():
        write_record(root, r)


def test_report_out_under_a_file_and_renders_not_there(world):
    tmp, res, snap = world
    _records_store(res)
    f = tmp / "afile"
    f.write_text("keep me")
    before = snap()
    rc, out, err = run_cli("report", "--results", str(res), "--out", str(f / "site"), "--no-previews", "--no-static-charts")
    one_line_error(rc, out, err, f"--out {f / 'site'}", f"cannot create the folder ({f} is not a folder)")
    site = tmp / "site"
    rc, out, err = run_cli("report", "--results", str(res), "--out", str(site), "--renders", str(tmp / "nonexistent"),
                           "--no-static-charts")
    one_line_error(rc, out, err, f"--renders {tmp / 'nonexistent'}", "no such folder")
    rc, out, err = run_cli("report", "--results", str(res), "--out", str(site), "--renders", str(f), "--no-static-charts")
    one_line_error(rc, out, err, f"--renders {f}", "is a file, not the folder")
    assert f.read_text() == "keep me" and not site.exists() and snap() == before


def test_verify_a_folder_without_records(tmp_path):
    from lmgs_eval.data.images import write_rgb

    empty = tmp_path / "empty"
    empty.mkdir()
    jpgs = tmp_path / "jpgs"
    jpgs.mkdir()
    for i in range(3):
        write_rgb(jpgs / f"{i}.jpg", np.full((16, 16, 3), 40 * i, np.uint8))
    for folder in (empty, jpgs):
        rc, out, err = run_cli("verify", str(folder))
        assert rc == 1 and "Traceback" not in err, (rc, out, err)
        assert err.strip() == (f"lmgs-eval verify: error: {folder}: no result records there, so nothing was checked "
                               "(give the results store, e.g. `lmgs-eval verify results`)")
        assert "all inputs unchanged" not in out


# ----------------------------------------------------------------------------- plans
PLAN = '[[stage]]\nprotocols = ["self"]\nsubjects = ["astronaut-64px-2s"]\nmethods = ["lmgs"]\n'


def test_a_plan_whose_cross_clip_is_missing(world):
    tmp, res, snap = world
    plan = tmp / "plan.toml"
    plan.write_text('[[stage]]\nprotocols = ["cross"]\nsubjects = ["astronaut-64px-2s"]\nmethods = ["lmgs"]\n'
                    'clips = ["gone.wav"]\n')
    before = snap()
    for extra in ([], ["--dry-run"]):
        rc, out, err = run_cli("run", str(plan), "--results", str(res / "r"), *extra)
        line = one_line_error(rc, out, err, "plan.toml: stage 1: clips:", "gone.wav: no such audio file")
        assert str(tmp / "gone.wav") in line
    assert snap() == before


@pytest.mark.parametrize("flags, words", [
    (["--max-parallel", "-3"], ["--max-parallel must be at least 1, got -3"]),
    (["--address", "10.0.0.1:6379"], ["--address names a Ray cluster; it needs --executor ray"]),
    (["--max-parallel", "2"], ["--max-parallel 2: the serial executor runs one at a time"]),
    (["--executor", "ray", "--address", "banana"], ["--address banana: expected auto or HOST:PORT"]),
])
def test_a_dry_run_checks_the_executor_flags_as_the_run_does(world, flags, words):
    tmp, res, snap = world
    plan = tmp / "plan.toml"
    plan.write_text(PLAN)
    before = snap()
    for extra in (["--dry-run"], []):
        rc, out, err = run_cli("run", str(plan), "--results", str(res / "r"), *flags, *extra)
        one_line_error(rc, out, err, *words)
        assert out == ""
    assert snap() == before


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_ray_address_with_no_cluster_is_refused_at_once(world):
    import time

    pytest.importorskip("ray")
    tmp, res, snap = world
    plan = tmp / "plan.toml"
    plan.write_text(PLAN)
    before = snap()
    address = f"127.0.0.1:{_free_port()}"  # nothing listens there
    t0 = time.perf_counter()
    rc, out, err = run_cli("run", str(plan), "--results", str(res / "r"), "--executor", "ray", "--address", address)
    one_line_error(rc, out, err, f"--address {address}: no Ray cluster there", "connection refused")
    assert time.perf_counter() - t0 < 30
    assert snap() == before


# ----------------------------------------------------------------------------- argparse
def test_argparse_errors_are_one_line(tmp_path, capsys):
    from lmgs_eval.cli import main

    for argv, want in (
        (["run", "x.toml", "--executor", "banana"], "lmgs-eval run: error: argument --executor: invalid choice: 'banana'"),
        (["self", "--seed", "x"], "lmgs-eval self: error: argument --seed: invalid int value: 'x'"),
        (["ingest"], "lmgs-eval ingest: error: the following arguments are required: video"),
        (["weights", "import-syncnet"], "lmgs-eval weights import-syncnet: error: the following arguments are required"),
        (["nosuch"], "lmgs-eval: error: argument COMMAND: invalid choice: 'nosuch'"),
    ):
        with pytest.raises(SystemExit) as e:
            main(argv)
        out, err = capsys.readouterr()
        assert e.value.code == 2 and out == ""
        assert len(err.strip().splitlines()) == 1 and err.startswith(want), err
    with pytest.raises(SystemExit) as e:  # --help still prints the usage, and exits 0
        main(["run", "--help"])
    out, err = capsys.readouterr()
    assert e.value.code == 0 and out.startswith("usage: lmgs-eval run") and "--max-parallel" in out
