"""PSNR / SSIM against scikit-image, streaming vs batch, registry and bad input."""

from __future__ import annotations

import numpy as np
import pytest
from skimage import data
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from lmgs_eval.errors import UserError
from lmgs_eval.metrics import Accumulator, create_metric, list_metrics
from lmgs_eval.metrics.base import Registry, align_lengths
from lmgs_eval.metrics.image import PSNR_CAP_DB, psnr, psnr_per_frame, ssim, ssim_per_frame


def _clips(seed=0, t=4, h=40, w=48):
    rng = np.random.default_rng(seed)
    gt = rng.random((t, h, w, 3)).astype(np.float32)
    pred = np.clip(gt + rng.normal(0, 0.1, gt.shape), 0, 1).astype(np.float32)
    return pred, gt


def _astronaut_pair():
    gt = data.astronaut()[96:352, 96:352].astype(np.float32) / 255.0
    rng = np.random.default_rng(1)
    pred = np.clip(gt + rng.normal(0, 0.04, gt.shape), 0, 1).astype(np.float32)
    return pred, gt


def _sk_ssim(p, g):
    return structural_similarity(p.astype(np.float64), g.astype(np.float64), gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False, data_range=1.0, channel_axis=-1)


def test_psnr_ssim_equal_skimage_random():
    pred, gt = _clips()
    ours_p = psnr_per_frame(pred, gt)
    ours_s = ssim_per_frame(pred, gt)
    for i in range(pred.shape[0]):
        assert ours_p[i] == pytest.approx(peak_signal_noise_ratio(gt[i].astype(np.float64), pred[i].astype(np.float64), data_range=1.0), abs=1e-9)
        assert ours_s[i] == pytest.approx(_sk_ssim(pred[i], gt[i]), abs=1e-10)


def test_psnr_ssim_equal_skimage_real_image():
    pred, gt = _astronaut_pair()
    assert psnr(pred, gt).value == pytest.approx(peak_signal_noise_ratio(gt.astype(np.float64), pred.astype(np.float64), data_range=1.0), abs=1e-9)
    assert ssim(pred, gt).value == pytest.approx(_sk_ssim(pred, gt), abs=1e-10)


def test_streaming_equals_batch():
    pred, gt = _clips(t=7)
    for name in ("psnr", "ssim"):
        m = create_metric(name)
        batch = m.compute(m.update(pred, gt))
        acc = Accumulator(create_metric(name))
        for s in (slice(0, 1), slice(1, 4), slice(4, 7)):
            acc.update(pred[s], gt[s])
        stream = acc.compute()
        np.testing.assert_array_equal(stream.per_item, batch.per_item)
        assert stream.value == batch.value and stream.n_effective == 7


def test_identical_frames_psnr_capped_and_flagged():
    _, gt = _clips(t=3)
    pred = gt.copy()
    pred[0] = np.clip(pred[0] + 0.1, 0, 1)
    r = psnr(pred, gt)
    assert r.per_item[1] == PSNR_CAP_DB and r.per_item[2] == PSNR_CAP_DB
    assert any("identical_frames: 2" in f for f in r.flags)
    assert ssim(gt, gt).value == pytest.approx(1.0, abs=1e-12)


def test_result_record_carries_spec_and_counts():
    pred, gt = _clips(t=2)
    d = psnr(pred, gt).to_dict()
    assert d["spec"]["name"] == "psnr" and d["spec"]["higher_is_better"] is True and d["spec"]["unit"] == "dB"
    assert d["n_original"] == 2 and d["n_effective"] == 2 and len(d["per_item"]) == 2


@pytest.mark.parametrize(
    "bad, msg",
    [
        (lambda g: (g * 255).astype(np.uint8), "dtype uint8"),
        (lambda g: g * 255.0, "range"),
        (lambda g: np.where(np.arange(g.shape[0])[:, None, None, None] == 1, np.nan, g), "frame 1 has non-finite"),
        (lambda g: g[..., :2], "RGB"),
    ],
)
def test_bad_frames_raise_user_error(bad, msg):
    pred, gt = _clips(t=3)
    with pytest.raises(UserError, match=msg):
        psnr(bad(pred), gt)


def test_different_lengths_need_truncate():
    with pytest.raises(UserError, match="pred has 5 frames but gt has 4"):
        align_lengths(5, 4, truncate=False)
    n, flags = align_lengths(5, 4, truncate=True)
    assert n == 4 and "truncated" in flags[0]


def test_registry_rejects_duplicates_and_unknown():
    r = Registry("metric")
    r.register("a", lambda: 1)
    with pytest.raises(ValueError):
        r.register("a", lambda: 2)
    with pytest.raises(TypeError):
        r.register("b", 3)
    with pytest.raises(UserError, match="unknown metric"):
        create_metric("nope")
    names = {m["name"] for m in list_metrics()}
    assert {"psnr", "ssim", "lpips-alex", "stlpips-alex", "lmd", "lse"} <= names
