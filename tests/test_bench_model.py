"""`lmgs-eval bench model`'s per-frame breakdown: every stage of a frame is timed and they add up.

The stages run for real, but the clock is a fake one that only the stages move, each by a fixed
cost per call (audio net 2 ms, the training forward 11 ms, the prepared deformation 3 ms, one
rasterization 5 ms, compositing 1 ms; of the image loss, 3DGS's SSIM 8 ms, the closed form's 2 ms,
the loss over the box 1 ms): every reported figure then has a value worked out by hand from which
calls a stage makes, independent of how fast this machine happens to be.
"""

from __future__ import annotations

import argparse
from types import SimpleNamespace

import pytest

from lmgs import bench

COST_MS = {"audio": 2.0, "forward": 11.0, "prepared": 3.0, "raster": 5.0, "composite": 1.0, "ssim_autograd": 8.0,
           "ssim": 2.0, "box": 1.0}


@pytest.fixture(scope="module")
def bench_out():
    import lmgs.model
    import lmgs.render
    from lmgs import losses
    from lmgs.audio import AudioNet
    from lmgs.deform import DeformNet

    now = [0.0]

    def costing(fn, key):
        def wrapped(*a, **k):
            out = fn(*a, **k)
            now[0] += COST_MS[key] / 1e3
            return out
        return wrapped

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(bench, "time", SimpleNamespace(perf_counter=lambda: now[0]))
        mp.setattr(AudioNet, "forward", costing(AudioNet.forward, "audio"))
        mp.setattr(DeformNet, "forward", costing(DeformNet.forward, "forward"))
        mp.setattr(DeformNet, "forward_prepared", costing(DeformNet.forward_prepared, "prepared"))
        mp.setattr(lmgs.render, "rasterize", costing(lmgs.render.rasterize, "raster"))
        mp.setattr(lmgs.model, "composite", costing(lmgs.model.composite, "composite"))
        mp.setattr(losses, "ssim_autograd", costing(losses.ssim_autograd, "ssim_autograd"))
        mp.setattr(losses, "ssim", costing(losses.ssim, "ssim"))
        mp.setattr(losses.CoveredPhotometric, "__call__", costing(losses.CoveredPhotometric.__call__, "box"))
        args = argparse.Namespace(points=[300], repeats=1, preset="quick", threads=0, sizes=[32, 48])
        return bench.run(args)


def test_frame_breakdown_times_each_stage_and_adds_them_up(bench_out):
    frames = bench_out["frames"]
    assert [(f["res"], f["points"]) for f in frames] == [("32x32", 300), ("48x48", 300)]
    for f in frames:
        # audio: one audio-net call; network: face and mouth deformed (2 x 3); raster: both branches
        # (2 x 5); compositing: one composite. 19 ms a frame, 1000 / 19 = 52.6 frames/s.
        assert (f["audio_ms"], f["network_ms"], f["raster_ms"], f["compositing_ms"]) == (2.0, 6.0, 10.0, 1.0)
        assert f["total_ms"] == 19.0 and f["frames_per_s"] == 52.6


def test_rows_time_the_prepared_deformation_beside_the_forward(bench_out):
    rows = {r["guidance"]: r for r in bench_out["rows"]}
    assert set(rows) == {"full (SE+LC)", "no SE/LC", "triplane fwd+bwd"}
    for name in ("full (SE+LC)", "no SE/LC"):
        r = rows[name]
        # per frame: audio (2) + the prepared deformation (3) = 5 ms, 200 frames/s; the training
        # forward (11) is 11 / 3 = 3.67x the prepared one
        assert (r["points"], r["audio_ms"], r["deform_ms"], r["forward_ms"]) == (300, 2.0, 3.0, 11.0), name
        assert (r["prepared_speedup"], r["total_ms"], r["frames_per_s"]) == (3.67, 5.0, 200.0), name
    tri = rows["triplane fwd+bwd"]
    assert tri["deform_ms"] == 0.0  # the encoder's step calls none of the stages above
    assert tri["forward_ms"] is None and tri["total_ms"] is None and tri["frames_per_s"] is None


def test_loss_rows_time_the_three_forms_of_the_image_loss(bench_out):
    loss = bench_out["loss"]
    assert [r["res"] for r in loss] == ["32x32", "48x48"]
    for r in loss:
        # each form's loss and backward: 3DGS's SSIM 8 ms, the closed form 2, the box 1 (its SSIM is
        # not :func:`ssim`: the box computes its own), so 4x and 8x
        assert (r["autograd_ms"], r["closed_form_ms"], r["box_ms"]) == (8.0, 2.0, 1.0)
        assert (r["closed_form_speedup"], r["box_speedup"]) == (4.0, 8.0)
        assert 0 < r["cover"] < 1  # the head covers part of the frame
