"""``lmgs-eval metrics`` and ``lmgs-eval score`` on frame folders (lengths, truncation recorded)."""

from __future__ import annotations

import json

import cv2
import numpy as np

from lmgs_eval.cli import main


def _folder(path, n, seed):
    path.mkdir()
    rng = np.random.default_rng(seed)
    for i in range(n):
        cv2.imwrite(str(path / f"{i}.png"), rng.integers(0, 256, (40, 40, 3), dtype=np.uint8))


def test_metrics_lists_backends(capsys):
    assert main(["metrics", "--json"]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert rows["psnr"]["available"] and rows["lse"]["name"] == "lse"


def test_score_folders_length_mismatch(tmp_path, capsys):
    _folder(tmp_path / "p", 11, 0)
    _folder(tmp_path / "g", 10, 1)
    args = ["score", "--pred", str(tmp_path / "p"), "--gt", str(tmp_path / "g"), "--metrics", "psnr,ssim"]
    assert main(args) == 2
    assert "pred has 11 frames but gt has 10" in capsys.readouterr().err
    assert main(args + ["--truncate", "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["n_frames"] == 10 and "truncated" in rec["flags"][0]
    assert rec["results"]["psnr"]["n_effective"] == 10 and any("truncated" in f for f in rec["results"]["ssim"]["flags"])


def test_bench_metrics_measures_every_metric_including_lse():
    import argparse

    from lmgs_eval.metrics import bench

    out = bench.run(argparse.Namespace(frames=2, sizes="128"))
    names = {r["metric"] for r in out["rows"]}
    assert {"psnr", "ssim", "lmd landmarks (dlib, pred+gt)"} <= names
    assert any(n.startswith("lse (bundled-sync") for n in names)  # the bundled scorer ships with the package
    eager = [r for r in out["rows"] if "eager" in r["metric"]]
    assert eager and all(r["ort_speedup"] > 0 for r in eager)
    assert all(r["frames_per_s"] > 0 and r["ms_per_frame"] > 0 for r in out["rows"])
    if out["lpips_network"] != "lpips-alex":  # the official network is timed anyway (random weights, named so)
        assert bench.ALEX_TIMING in names and "random weights" in bench.ALEX_TIMING


def test_score_names_a_trunk_that_is_not_torchvisions_lpips_alex_custom(tmp_path, capsys):
    import pytest
    import torch

    from conftest import random_alexnet_state
    from lmgs_eval.metrics import lpips as L

    if L.lpips_heads_path() is None:
        pytest.skip("lpips wheel not installed")
    _folder(tmp_path / "p", 2, 0)
    _folder(tmp_path / "g", 2, 1)
    ck = tmp_path / L.ALEXNET_CKPT  # torchvision's file name, random weights
    torch.save(random_alexnet_state(), ck)
    sha = L.sha256_file(ck)
    args = ["score", "--pred", str(tmp_path / "p"), "--gt", str(tmp_path / "g"), "--metrics", "lpips",
            "--alexnet", str(ck)]
    assert main(args + ["--json"]) == 0
    out = capsys.readouterr()
    rec = json.loads(out.out)
    assert list(rec["results"]) == ["lpips-alex-custom"]
    spec = rec["results"]["lpips-alex-custom"]["spec"]
    assert spec["name"] == "lpips-alex-custom" and "not comparable with published LPIPS" in spec["standin"]
    assert spec["weights_files"]["alexnet"] == {"path": str(ck.resolve()), "sha256": sha}
    assert spec["weights_files"]["lpips_heads"]["sha256"] == L.LPIPS_HEADS_SHA256
    said = [ln for ln in out.err.splitlines() if "lpips-alex-custom" in ln]
    assert len(said) == 1 and str(ck) in said[0] and sha[:8] in said[0] and "not torchvision's published" in said[0]
    assert main(["metrics", "--json", "--alexnet", str(ck)]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert not rows["lpips-alex"]["available"] and "lpips-alex-custom" in rows["lpips-alex"]["detail"]
    assert rows["lpips-alex-custom"]["available"] and sha[:8] in rows["lpips-alex-custom"]["detail"]
