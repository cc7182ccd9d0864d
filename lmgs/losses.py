"""Losses of the reference model: L1, D-SSIM, and the Geometry Regularizer.

.. math::
    \\mathcal{L}_D = L1(I, I_G) + \\lambda\\,\\mathcal{L}_{D\\text{-}SSIM}(I, I_G) + \\mathcal{L}_{Geo}

    \\mathcal{L}_{Geo} = \\lambda_D L_D(D, \\tilde D) + \\lambda_N \\sum_{i,j} (1 - N_{ij} \\cdot \\tilde N_{ij})

(paper, "Geometry Regularizer" and "Training Detail"; :math:`\\lambda_D = \\lambda_N = 10^{-4}`;
:math:`\\lambda = 0.2` as in 3DGS / TalkingGaussian).

On the CPU the image loss took about half of a training step at 512 px when computed as 3DGS's
code does (:func:`ssim_autograd`: ten depthwise convolutions and autograd's record of a dozen
full-size operations). :func:`ssim` has the same value with its gradient in closed form (numba
kernels on the CPU), and a training step computes the loss over the box around the head only
(:class:`CoveredPhotometric`), where the render is not its background: the same value and
gradient up to float rounding.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def _gauss_window(size: int = 11, sigma: float = 1.5, device=None, dtype=torch.float32) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


SSIM_RADIUS = 5  # the SSIM window's half width: 11 taps
TILE = 16  # pixels: the grid the box of :class:`CoveredPhotometric` is drawn on


def _blur(t: torch.Tensor) -> torch.Tensor:
    """The SSIM window's Gaussian over each channel of ``[1, C, h + 10, w + 10]``, without padding:
    ``[1, C, h, w]``: one separable depthwise convolution (torch's) for all the channels."""
    g = _gauss_window(device=t.device, dtype=t.dtype)
    c = t.shape[1]
    wx = g.view(1, 1, 1, -1).expand(c, 1, 1, -1)
    wy = g.view(1, 1, -1, 1).expand(c, 1, -1, 1)
    return F.conv2d(F.conv2d(t, wx, groups=c), wy, groups=c)


_C1, _C2 = 0.01**2, 0.03**2  # also lmgs._ssim_numba.C1, C2 (the numba kernels)


def _ssim_factors(mx, my, exx, eyy, exy):
    """SSIM's ``A1 = 2 mx my + c1``, ``A2 = 2 sxy + c2``, ``B1 = mx^2 + my^2 + c1``, ``B2 = sxx + syy + c2``
    (``s = A1 A2 / (B1 B2)``) from the window's means of x, y, x^2, y^2 and xy."""
    return (2 * mx * my + _C1, 2 * (exy - mx * my) + _C2, mx * mx + my * my + _C1,
            (exx - mx * mx) + (eyy - my * my) + _C2)


def _on_numba(t: torch.Tensor) -> bool:
    return t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64)


class _SSIMMap(torch.autograd.Function):
    """``apply(x, y)``: the SSIM map ``[1, C, h, w]`` of images ``[1, C, h + 10, w + 10]`` (each inner
    pixel's window inside the inputs, no padding here), with its gradient in closed form (as the
    fused SSIM kernels of 3DGS implementations do), not through autograd's record of a dozen
    full-size operations. On the CPU both directions run in numba (:mod:`lmgs._ssim_numba`).

    With ``mx = G*x``, ``sxx = G*x^2 - mx^2``, ``sxy = G*(xy) - mx my`` (``G`` the window), ``A1 = 2 mx my
    + c1``, ``A2 = 2 sxy + c2``, ``B1 = mx^2 + my^2 + c1``, ``B2 = sxx + syy + c2`` and ``s = A1 A2 / (B1 B2)``:
    ``ds/dmx = 2 s (my / A1 - my / A2 - mx / B1 + mx / B2)`` (through ``sxx`` and ``sxy`` too),
    ``ds/d(G*x^2) = -s / B2``, ``ds/d(G*xy) = 2 s / A2``, so for an upstream gradient ``g`` on the map,
    ``dL/dx = G'*(g ds/dmx) + 2 x G'*(g ds/d(G*x^2)) + y G'*(g ds/d(G*xy))`` with ``G'`` the window's
    transpose (the same Gaussian, with full padding); ``y``'s by symmetry."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if _on_numba(x) and y.dtype == x.dtype:
            from lmgs import _ssim_numba

            xn, yn = (t[0].detach().contiguous().numpy() for t in (x, y))
            g = _gauss_window(dtype=x.dtype).numpy()
            s, terms = _ssim_numba.forward(xn, yn, g, want_y=bool(ctx.needs_input_grad[1]))
            ctx.numba = (xn, yn, g, terms)
            return torch.from_numpy(s)[None]
        ctx.numba = None
        mx, my, exx, eyy, exy = _blur(torch.cat([x, y, x * x, y * y, x * y], 1)).split(x.shape[1], 1)
        a1, a2, b1, b2 = _ssim_factors(mx, my, exx, eyy, exy)
        s = (a1 * a2) / (b1 * b2)
        ctx.save_for_backward(x, y, mx, my, a1, a2, b1, b2, s)
        return s

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        want_x, want_y = (bool(w) for w in ctx.needs_input_grad[:2])
        if ctx.numba is not None:
            from lmgs import _ssim_numba

            xn, yn, win, terms = ctx.numba
            gx, gy = _ssim_numba.backward(g[0].detach().contiguous().numpy(), xn, yn, win, terms, want_x, want_y)
            return tuple(None if t is None else torch.from_numpy(t)[None] for t in (gx, gy))
        x, y, mx, my, a1, a2, b1, b2, s = ctx.saved_tensors
        gs = g * s
        common = (-gs / b2, 2 * gs / a2)  # d/d(G*x^2) (and G*y^2), d/d(G*xy)
        maps, pick = [], []
        if want_x:
            maps.append(2 * gs * (my / a1 - my / a2 - mx / b1 + mx / b2))
            pick.append("x")
        if want_y:
            maps.append(2 * gs * (mx / a1 - mx / a2 - my / b1 + my / b2))
            pick.append("y")
        r = (x.shape[-1] - s.shape[-1]) // 2  # the window's half width
        full = _blur(F.pad(torch.cat([*maps, *common], 1), (2 * r, 2 * r, 2 * r, 2 * r)))
        c = x.shape[1]
        parts = dict(zip(pick, full.split(c, 1)))
        t_sq, t_xy = full[:, -2 * c:].split(c, 1)
        gx = parts["x"] + 2 * x * t_sq + y * t_xy if want_x else None
        gy = parts["y"] + 2 * y * t_sq + x * t_xy if want_y else None
        return gx, gy


def _window(img: torch.Tensor, y0: int, y1: int, x0: int, x1: int, r: int = SSIM_RADIUS) -> torch.Tensor:
    """Rows ``y0:y1``, columns ``x0:x1`` of ``[H, W, C]`` as ``[1, C, h + 2r, w + 2r]`` with ``r`` pixels
    of context on each side, zeros beyond the image (as the full frame's zero padding)."""
    h, w = img.shape[:2]
    a, b, c, d = max(y0 - r, 0), min(y1 + r, h), max(x0 - r, 0), min(x1 + r, w)
    t = img[a:b, c:d].permute(2, 0, 1)[None]
    pad = (c - (x0 - r), (x1 + r) - d, a - (y0 - r), (y1 + r) - b)
    return F.pad(t, pad) if any(pad) else t


def ssim_map(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """SSIM map ``[1, 3, H, W]`` of ``[H, W, 3]`` images in [0, 1] (Gaussian window 11, sigma 1.5,
    zero padding at the frame's edges, as 3DGS's loss)."""
    h, w = img.shape[:2]
    return _SSIMMap.apply(_window(img, 0, h, 0, w), _window(ref, 0, h, 0, w))


def ssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of ``[H, W, 3]`` images in [0, 1] (Gaussian window 11, sigma 1.5, as 3DGS's loss;
    :func:`ssim_autograd`'s value, its gradient in closed form)."""
    return ssim_map(img, ref).mean()


def ssim_autograd(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """:func:`ssim` as 3DGS's training code computes it: each statistic a depthwise convolution
    (torch's) of the zero-padded images, differentiated by autograd. The form :func:`ssim`
    replaces, timed beside it by ``lmgs-eval bench model``."""
    h, w = img.shape[:2]
    x, y = _window(img, 0, h, 0, w), _window(ref, 0, h, 0, w)
    a1, a2, b1, b2 = _ssim_factors(_blur(x), _blur(y), _blur(x * x), _blur(y * y), _blur(x * y))
    return ((a1 * a2) / (b1 * b2)).mean()


def photometric(img: torch.Tensor, ref: torch.Tensor, lambda_dssim: float = 0.2, *, ssim_fn=None) -> torch.Tensor:
    """``(1 - λ) L1 + λ (1 - SSIM)``, the 3DGS / TalkingGaussian image loss (``ssim_fn``: default :func:`ssim`)."""
    return (1 - lambda_dssim) * (img - ref).abs().mean() + lambda_dssim * (1 - (ssim_fn or ssim)(img, ref))


def _tile_table(per_pixel: torch.Tensor, tile: int = TILE) -> torch.Tensor:
    """Summed-area table ``[TH + 1, TW + 1]`` (float64, on the host) of ``[H, W]`` summed over
    ``tile x tile`` tiles (the last row and column of tiles may be partial)."""
    h, w = per_pixel.shape
    th, tw = -(-h // tile), -(-w // tile)
    p = F.pad(per_pixel.detach().double().cpu(), (0, tw * tile - w, 0, th * tile - h))
    sums = p.reshape(th, tile, tw, tile).sum((1, 3))
    return F.pad(sums.cumsum(0).cumsum(1), (1, 0, 1, 0))


class CoveredPhotometric:
    """:func:`photometric` of a render that is exactly its background wherever no Gaussian covers
    it, computed over the box around what the Gaussians cover.

    Outside the covered pixels the render does not depend on the model, so neither do the L1
    terms there, nor the SSIM terms whose 11-pixel window does not reach a covered pixel: the
    gradient comes from the box alone. The box is the covered pixels' bounding box grown by one
    :data:`TILE` (more than the window's reach) and drawn on the tile grid; the loss's value adds
    the terms outside the box, those of the background against the frame, from tables made the
    first time each frame is seen (a full-frame SSIM of background and frame, kept as per-tile
    sums). Value and gradient are :func:`photometric`'s up to float rounding, at the cost of the
    box: with the head on a quarter of a 512x512 frame, three quarters of the closed form's over
    the whole frame (``lmgs-eval bench model``). On a GPU, where finding the box would make the
    host wait for the device, it is :func:`photometric` over the whole frame.
    """

    def __init__(self, lambda_dssim: float = 0.2, tile: int = TILE) -> None:
        self.lambda_dssim = lambda_dssim
        self.tile = tile
        self._outside: dict = {}  # frame key -> (L1 table, SSIM table) over tiles

    def _tables(self, key, bg: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        found = self._outside.get(key)
        if found is None:
            with torch.no_grad():
                l1 = (bg - ref).abs().sum(-1)
                s = ssim_map(bg, ref)[0].sum(0)
            found = self._outside[key] = (_tile_table(l1, self.tile), _tile_table(s, self.tile))
        return found

    def __call__(self, img: torch.Tensor, ref: torch.Tensor, bg: torch.Tensor, cover: torch.Tensor, key) -> torch.Tensor:
        """``img``, ``ref``, ``bg``: ``[H, W, 3]``; ``cover``: ``[H, W]`` bool, the pixels some
        Gaussian reaches (the render equals ``bg`` elsewhere); ``key``: the frame (``ref`` and
        ``bg`` are the same for a key on every call)."""
        if img.device.type != "cpu":
            return photometric(img, ref, self.lambda_dssim)
        h, w = img.shape[:2]
        rows, cols = torch.nonzero(cover.any(1)), torch.nonzero(cover.any(0))
        if len(rows) == 0:
            return photometric(img, ref, self.lambda_dssim)
        t = self.tile
        ty0, ty1 = max(int(rows[0]) // t - 1, 0), min(int(rows[-1]) // t + 2, -(-h // t))
        tx0, tx1 = max(int(cols[0]) // t - 1, 0), min(int(cols[-1]) // t + 2, -(-w // t))
        y0, y1, x0, x1 = ty0 * t, min(ty1 * t, h), tx0 * t, min(tx1 * t, w)
        l1_tab, s_tab = self._tables(key, bg, ref)

        def outside(tab: torch.Tensor) -> float:
            inside = tab[ty1, tx1] - tab[ty0, tx1] - tab[ty1, tx0] + tab[ty0, tx0]
            return float(tab[-1, -1] - inside)

        n = 3.0 * h * w
        l1 = ((img[y0:y1, x0:x1] - ref[y0:y1, x0:x1]).abs().sum() + outside(l1_tab)) / n
        s = (_SSIMMap.apply(_window(img, y0, y1, x0, x1), _window(ref, y0, y1, x0, x1)).sum() + outside(s_tab)) / n
        return (1 - self.lambda_dssim) * l1 + self.lambda_dssim * (1 - s)


def scale_invariant_depth(depth: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor, gather: bool = True) -> torch.Tensor:
    """Scale-invariant log-depth loss (Eigen et al. 2014) over ``mask``.

    .. math:: L_D = \\frac1n \\sum \\delta^2 - \\frac1{n^2} (\\sum \\delta)^2, \\quad \\delta = \\log D - \\log \\tilde D

    ``gather=False`` sums over the whole image with the mask as weights instead of selecting the
    masked pixels: the same value up to the order of float sums, and nothing read back from the
    device (selecting by a mask, or testing how many pixels it holds, waits for a GPU).
    """
    m = mask & (ref > 0) & (depth > 1e-6)
    if not gather:
        n = m.to(depth.dtype).sum()
        d = torch.where(m, torch.log(torch.where(m, depth, 1.0)) - torch.log(torch.where(m, ref, 1.0)), 0.0)
        mean = d.sum() / n.clamp_min(1.0)
        return torch.where(n >= 2, (d * d).sum() / n.clamp_min(1.0) - mean**2, depth.sum() * 0.0)
    n = m.sum()
    if n < 2:
        return depth.sum() * 0.0
    d = torch.log(depth[m]) - torch.log(ref[m])
    return (d**2).mean() - d.mean() ** 2


def normal_loss(normal: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor, reduce: str = "sum",
                gather: bool = True) -> torch.Tensor:
    """:math:`\\sum_{ij} (1 - N_{ij} \\cdot \\tilde N_{ij})` over ``mask``.

    ``reduce="sum"`` is the paper's formula; ``"mean"`` divides by the masked pixel count (the
    per-pixel normal terms of 2DGS / PGSR), so its weight does not grow with the face's area.
    ``gather=False``: masked sums, as in :func:`scale_invariant_depth`.
    """
    if reduce not in ("sum", "mean"):
        raise ValueError(f"normal_loss: reduce must be 'sum' or 'mean', not {reduce!r}")
    n = F.normalize(normal, dim=-1, eps=1e-6)
    per_pixel = 1.0 - (n * ref).sum(-1)
    if not gather:
        total = torch.where(mask, per_pixel, 0.0).sum()
        return total if reduce == "sum" else total / mask.sum().clamp_min(1).to(total.dtype)
    err = per_pixel[mask]
    if reduce == "sum":
        return err.sum()
    return err.mean() if err.numel() else err.sum()


def geometry(
    depth: torch.Tensor, normal: torch.Tensor, alpha: torch.Tensor, ref_depth: torch.Tensor, ref_normal: torch.Tensor,
    lambda_d: float = 1e-4, lambda_n: float = 1e-4, normal_reduce: str = "sum", gather: bool = True,
) -> torch.Tensor:
    """The Geometry Regularizer on pixels where both the render and the reference have a surface.

    ``depth`` is the alpha-normalised expected depth ``[H, W, 1]``; ``normal`` ``[H, W, 3]``.
    ``gather=False`` computes both terms as masked sums (:func:`scale_invariant_depth`): equal up to
    float rounding, and no read-back on a GPU. A term of weight 0 is not computed (its normals,
    ``normal`` and ``ref_normal``, may then be None): it would add exactly zero to the loss and to
    every gradient, at the cost of its forward and backward passes over the frame.
    """
    mask = (alpha[..., 0] > 0.5) & (ref_depth > 0)
    loss = depth.sum() * 0.0 if lambda_d == 0 else lambda_d * scale_invariant_depth(depth[..., 0], ref_depth, mask, gather)
    if lambda_n != 0:
        loss = loss + lambda_n * normal_loss(normal, ref_normal, mask, normal_reduce, gather)
    return loss
