"""`lmgs-eval bench model`'s per-frame breakdown: every stage of a frame is timed and they add up."""

from __future__ import annotations

import argparse

import pytest

from lmgs import bench


def test_frame_breakdown_times_each_stage_and_adds_them_up():
    args = argparse.Namespace(points=[300], repeats=1, preset="quick", threads=0, sizes=[32, 48])
    out = bench.run(args)
    frames = out["frames"]
    assert [(f["res"], f["points"]) for f in frames] == [("32x32", 300), ("48x48", 300)]
    for f in frames:
        parts = [f[k] for k in ("audio_ms", "network_ms", "raster_ms", "compositing_ms")]
        assert all(v > 0 for v in parts)
        assert f["total_ms"] == pytest.approx(sum(parts), abs=2e-3)
        assert f["frames_per_s"] == pytest.approx(1e3 / f["total_ms"], abs=0.05)


def test_rows_time_the_prepared_deformation_beside_the_forward():
    args = argparse.Namespace(points=[300], repeats=1, preset="quick", threads=0, sizes=[32])
    rows = [r for r in bench.run(args)["rows"] if r["forward_ms"] is not None]
    assert {r["guidance"] for r in rows} == {"full (SE+LC)", "no SE/LC"}
    for r in rows:
        assert r["deform_ms"] > 0 and r["forward_ms"] > 0
        assert r["prepared_speedup"] == pytest.approx(r["forward_ms"] / r["deform_ms"], rel=0.02)
