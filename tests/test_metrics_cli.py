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


def test_bench_metrics_measures_every_metric_including_lse(monkeypatch):
    """Every metric is timed and turned into its figures; the clock is a fake one that each read
    moves by 1 ms and each metric call by a fixed cost, so every figure is worked out by hand.
    The sizes are labelled 512 (for the suite estimate) but the frames are 64 px (cheap)."""
    import argparse
    from types import SimpleNamespace

    import pytest

    from lmgs_eval.metrics import bench
    from lmgs_eval.metrics.landmarks import DlibBackend
    from lmgs_eval.metrics.lpips import LPIPS

    now = [0.0]

    def clock():
        now[0] += 1e-3
        return now[0]

    def costing(fn, ms):
        def wrapped(*a, **k):
            out = fn(*a, **k)
            now[0] += (ms(a[0]) if callable(ms) else ms) / 1e3
            return out
        return wrapped

    clip = bench._clip
    monkeypatch.setattr(bench, "_clip", lambda n, size: clip(n, 64))
    monkeypatch.setattr(bench, "time", SimpleNamespace(perf_counter=clock))
    monkeypatch.setattr(bench, "psnr_per_frame", costing(bench.psnr_per_frame, 3))
    monkeypatch.setattr(bench, "ssim_per_frame", costing(bench.ssim_per_frame, 7))
    monkeypatch.setattr(bench, "lse", costing(bench.lse, 60))
    monkeypatch.setattr(DlibBackend, "landmarks", costing(DlibBackend.landmarks, 10))
    monkeypatch.setattr(LPIPS, "distances", costing(LPIPS.distances, lambda lp: 30 if lp.spec.name == "lpips-alex" else 20))

    out = bench.run(argparse.Namespace(frames=2, sizes="512"))
    net = out["lpips_network"]
    official = net == "lpips-alex"  # torchvision's trunk installed: no separate timing of the official shape
    assert out["frames"] == 2
    rows = {r["metric"]: r for r in out["rows"]}
    assert {r["size"] for r in out["rows"]} == {512} and len(rows) == len(out["rows"])
    lse_name = "lse (bundled-sync, detect+crop+embed)"  # the bundled scorer ships with the package
    # a timing is the costs of its calls + 1 ms (the clock read that ends it), over 2 frames
    # (LSE: over 50, its whole windows): ms/frame and frames/s of each
    ort = 15.5 if official else 10.5
    want = {"psnr": 2.0, "ssim": 4.0, f"{net} onnxruntime": ort, f"{net} eager torch (folded)": 0.5,
            f"{net} eager torch (reference)": 0.5, "lmd landmarks (dlib, pred+gt)": 10.5, lse_name: 61 / 50}
    if not official:
        want[bench.ALEX_TIMING] = 15.5
        assert "random weights" in bench.ALEX_TIMING
    assert set(rows) == set(want)
    for name, ms in want.items():
        r = rows[name]
        assert r["ms_per_frame"] == pytest.approx(ms) and r["frames_per_s"] == pytest.approx(1e3 / ms), name
        assert r["ort_speedup"] == (pytest.approx(0.5 / ort) if "eager" in name else None), name
    # 500 frames of PSNR + SSIM + LPIPS (ORT) + LMD + LSE: 2 + 4 + 10.5 + 10.5 + 1.22 = 28.22 ms a frame;
    # with the ground truth's landmarks cached half the LMD less (22.97 ms); with the official
    # network's 15.5 ms for the 10.5: 33.22 and 27.97 ms
    estimates = {k: v for k, v in out.items() if k.startswith("suite_500x512") and not k.endswith("note")}
    if official:
        assert estimates == {"suite_500x512_estimate_s": 16.6, "suite_500x512_gt_cached_estimate_s": 14.0}
    else:
        assert estimates == {"suite_500x512_estimate_s": 14.1, "suite_500x512_gt_cached_estimate_s": 11.5,
                             "suite_500x512_lpips_alex_estimate_s": 16.6,
                             "suite_500x512_lpips_alex_gt_cached_estimate_s": 14.0}
    assert "+LSE" in out["suite_estimate_note"]


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
