"""Closed-form full-reference image metrics: PSNR and SSIM, per frame then mean.

Both take float frames ``[T, H, W, 3]`` in [0, 1] (data range 1), full frame, no crop,
which is how ER-NeRF and TalkingGaussian score (docs/field.md, "Metric definitions").
"""

from __future__ import annotations

import numpy as np

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import FloatFrames, MetricResult, MetricSpec, check_pair, mean_result

PSNR_CAP_DB = 100.0
"""PSNR of identical frames (MSE 0, mathematically +inf) is reported as this cap, flagged."""

PSNR_SPEC = MetricSpec(
    name="psnr",
    higher_is_better=True,
    unit="dB",
    backend="numpy",
    version="1",
    definition=(
        "per frame PSNR = -10 log10(mean((pred - gt)^2)) over all pixels and RGB channels of "
        "[0,1] frames (data range 1), computed in float64; mean over frames. A frame with MSE 0 "
        f"(identical) is capped at {PSNR_CAP_DB:g} dB and flagged."
    ),
    reference="ER-NeRF / TalkingGaussian evaluation; equals skimage.metrics.peak_signal_noise_ratio(data_range=1)",
)

SSIM_SPEC = MetricSpec(
    name="ssim",
    higher_is_better=True,
    unit="",
    backend="opencv-float64",
    version="1",
    definition=(
        "Wang et al. 2004 SSIM, per channel, Gaussian window sigma=1.5 truncated at 3.5 sigma (11 taps), "
        "population (not sample) covariance, K1=0.01, K2=0.03, data range 1; the SSIM map is averaged "
        "over the pixels at least 5 px from the border and over the 3 channels; float64; mean over frames. "
        "Identical to skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5, "
        "use_sample_covariance=False, data_range=1, channel_axis=-1)."
    ),
    reference="Wang, Bovik, Sheikh, Simoncelli, IEEE TIP 2004; scikit-image structural_similarity",
)


# ----------------------------------------------------------------------------- PSNR
def psnr_per_frame(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Uncapped per-frame PSNR in dB (``inf`` where the frames are identical).

    .. math:: \\mathrm{PSNR}_t = -10 \\log_{10} \\frac{1}{HWC} \\sum (\\hat x - x)^2

    Args:
        pred: ``[T, H, W, 3]`` float in [0, 1].
        gt: same shape.
    """
    pred, gt = check_pair(pred, gt)
    t = pred.shape[0]
    mse = np.empty(t, np.float64)
    for i in range(t):  # frame by frame: no [T, H, W, 3] float64 temporary
        d = pred[i].astype(np.float64) - gt[i].astype(np.float64)
        mse[i] = np.mean(d * d)
    with np.errstate(divide="ignore"):
        return -10.0 * np.log10(mse)


class PSNR(FloatFrames):
    """PSNR metric: ``update`` -> per-frame dB, ``compute`` -> mean with the cap flag."""

    spec = PSNR_SPEC

    def update(self, pred: np.ndarray, gt: np.ndarray) -> dict[str, np.ndarray]:
        return {"per_item": psnr_per_frame(pred, gt)}

    def compute(self, stats: dict[str, np.ndarray]) -> MetricResult:
        v = np.asarray(stats["per_item"], np.float64)
        flags = []
        n_inf = int(np.isposinf(v).sum())
        if n_inf:
            flags.append(f"identical_frames: {n_inf} frame(s) with MSE 0 capped at {PSNR_CAP_DB:g} dB")
        return mean_result(self.spec, np.minimum(v, PSNR_CAP_DB), flags)


def psnr(pred: np.ndarray, gt: np.ndarray) -> MetricResult:
    """Mean PSNR over frames (see :data:`PSNR_SPEC`)."""
    m = PSNR()
    return m.compute(m.update(pred, gt))


def psnr_outside(pred: np.ndarray, gt: np.ndarray, exclude: np.ndarray) -> float:
    """The toolkit's PSNR (dB; per frame, then the mean over frames; an identical frame capped as
    the metric caps it) of uint8 or [0, 1] frames ``[T, H, W, 3]`` over the pixels not in
    ``exclude`` ``[T, H, W]``; frames with no pixel left are skipped (NaN when none is left)."""

    def unit(x):
        x = np.asarray(x)
        return x.astype(np.float64) / 255.0 if x.dtype == np.uint8 else x.astype(np.float64)

    keep = ~np.asarray(exclude, bool)
    vals = []
    for t in range(len(keep)):
        if keep[t].any():
            mse = float(np.mean(((unit(pred[t]) - unit(gt[t])) ** 2).mean(-1)[keep[t]]))
            vals.append(PSNR_CAP_DB if mse == 0 else min(PSNR_CAP_DB, -10 * np.log10(mse)))
    return float(np.mean(vals)) if vals else float("nan")


# ----------------------------------------------------------------------------- SSIM
SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5
SSIM_K1, SSIM_K2 = 0.01, 0.03


def _gauss1d(sigma: float = SSIM_SIGMA, truncate: float = SSIM_TRUNCATE) -> np.ndarray:
    """scipy.ndimage's Gaussian taps: radius ``int(truncate * sigma + 0.5)``, normalised."""
    r = int(truncate * sigma + 0.5)
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def ssim_per_frame(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-frame SSIM (Wang et al. 2004), float64, all moments of a frame filtered at once.

    .. math::
        \\mathrm{SSIM} = \\frac{(2\\mu_x\\mu_y + C_1)(2\\sigma_{xy} + C_2)}
                              {(\\mu_x^2 + \\mu_y^2 + C_1)(\\sigma_x^2 + \\sigma_y^2 + C_2)},
        \\quad C_1 = (0.01)^2,\\ C_2 = (0.03)^2

    with Gaussian-weighted local moments (sigma 1.5, 11 taps), population covariance.
    skimage pads with 'reflect' and then discards a border of 5 px (the window radius):
    the kept pixels never see the padding, so any border mode gives the kept region
    exactly. The 15 moment maps of a frame (5 per channel) are kept as contiguous planes
    and each is filtered by OpenCV's separable filter (SIMD, threaded); the combination
    runs in place on contiguous float64 planes (about 2x faster than interleaved channels).

    Args:
        pred: ``[T, H, W, 3]`` float in [0, 1], H and W at least 11.
        gt: same shape.
    """
    import cv2


    pred, gt = check_pair(pred, gt)
    t, h, w, c = pred.shape
    g = _gauss1d()
    r = g.shape[0] // 2
    if h < 2 * r + 1 or w < 2 * r + 1:
        raise UserError(f"ssim: frames must be at least {2 * r + 1}x{2 * r + 1} pixels, got {h}x{w}")
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    out = np.empty(t, np.float64)
    st = np.empty((5, c, h, w), np.float64)  # x, y, xx, yy, xy
    f = np.empty((5, c, h - 2 * r, w - 2 * r), np.float64)
    for i in range(t):
        x, y = st[0], st[1]
        x[...] = pred[i].transpose(2, 0, 1)
        y[...] = gt[i].transpose(2, 0, 1)
        np.multiply(x, x, out=st[2])
        np.multiply(y, y, out=st[3])
        np.multiply(x, y, out=st[4])
        for k in range(5):
            for ch in range(c):
                f[k, ch] = cv2.sepFilter2D(st[k, ch], -1, g, g, borderType=cv2.BORDER_REFLECT)[r:h - r, r:w - r]
        mx, my, exx, eyy, exy = f
        mxy = mx * my
        mm = mx * mx
        mm += my * my  # mu_x^2 + mu_y^2
        num = 2 * mxy
        num += c1
        cov = exy - mxy
        cov *= 2
        cov += c2
        num *= cov  # (2 mu_x mu_y + C1)(2 sigma_xy + C2)
        var = exx + eyy
        var -= mm
        var += c2
        den = mm + c1
        den *= var  # (mu_x^2 + mu_y^2 + C1)(sigma_x^2 + sigma_y^2 + C2)
        num /= den
        out[i] = float(num.mean())
    return out


class SSIM(FloatFrames):
    """SSIM metric (see :data:`SSIM_SPEC`)."""

    spec = SSIM_SPEC

    def update(self, pred: np.ndarray, gt: np.ndarray) -> dict[str, np.ndarray]:
        return {"per_item": ssim_per_frame(pred, gt)}

    def compute(self, stats: dict[str, np.ndarray]) -> MetricResult:
        return mean_result(self.spec, stats["per_item"], [])


def ssim(pred: np.ndarray, gt: np.ndarray) -> MetricResult:
    """Mean SSIM over frames (see :data:`SSIM_SPEC`)."""
    m = SSIM()
    return m.compute(m.update(pred, gt))
