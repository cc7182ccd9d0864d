"""The functional entry point :func:`rasterize` and its typed result."""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass
from typing import Literal

import torch

from lmgs.errors import InputError
from lmgs.render._projection import check_inputs, project, view_colors
from lmgs.types import Camera

Backend = Literal["auto", "numba", "torch", "gsplat", "triton"]
BACKENDS: tuple[str, ...] = ("auto", "numba", "torch", "gsplat", "triton")
RenderMode = Literal["RGB+D+N", "RGB"]
# features composited per pixel in each mode (rgb, depth, normal: see the kernels' row layout)
_MODE_FEATURES: dict[str, int] = {"RGB+D+N": 7, "RGB": 3}
RENDER_MODES: tuple[str, ...] = tuple(_MODE_FEATURES)


@dataclass(frozen=True)
class RasterResult:
    """What :func:`rasterize` returns.

    Images (``H x W`` of the camera), with per-pixel weights
    :math:`w_i = \\alpha_i T_{i-1}` of the Gaussians composited front to back:

    Attributes:
        rgb: ``[H, W, 3]`` :math:`\\sum_i w_i c_i + T_n \\cdot bg` (no background term
            when ``background`` is None).
        alpha: ``[H, W, 1]`` :math:`\\sum_i w_i = 1 - T_n`.
        depth: ``[H, W, 1]`` :math:`\\sum_i w_i z_i`, camera z accumulated and **not**
            normalised by alpha (gsplat's ``"D"``); see :attr:`expected_depth`. None with
            ``render_mode="RGB"``.
        normal: ``[H, W, 3]`` :math:`\\sum_i w_i n_i`, camera-space (OpenCV) unit axis of
            each Gaussian's smallest scale, oriented towards the camera; not normalised. None
            with ``render_mode="RGB"``.
        radii: ``[N]`` int32 screen radius in pixels (3 sigma), 0 = culled.
        visible: ``[N]`` bool, ``radii > 0``.
        means2d: ``[N, 2]`` pixel positions, a node of the autograd graph with
            ``retain_grad()`` already called: after ``backward()``, ``means2d.grad`` is
            the 2D positional gradient used for densification (gsplat's
            ``absgrad=False``). Zero rows for culled Gaussians.
    """

    rgb: torch.Tensor  # [H, W, 3]
    alpha: torch.Tensor  # [H, W, 1]
    depth: torch.Tensor | None  # [H, W, 1]
    normal: torch.Tensor | None  # [H, W, 3]
    radii: torch.Tensor  # [N] int32
    visible: torch.Tensor  # [N] bool
    means2d: torch.Tensor  # [N, 2]

    @property
    def expected_depth(self) -> torch.Tensor:
        """``[H, W, 1]`` :math:`\\sum_i w_i z_i / \\max(\\sum_i w_i, 10^{-10})` (0 where empty)."""
        return self.depth / self.alpha.clamp_min(1e-10)


def rasterize(
    means: torch.Tensor,  # [N, 3] world positions
    quats: torch.Tensor,  # [N, 4] rotations, wxyz, any norm (normalised here)
    log_scales: torch.Tensor,  # [N, 3] log of the standard deviations along the axes
    opacity_logits: torch.Tensor,  # [N] opacity = sigmoid(logit)
    colors: torch.Tensor,  # [N, 3] rgb, or [N, K, 3] SH coefficients
    camera: Camera,
    background: torch.Tensor | None = None,  # [3]
    *,
    sh_degree: int | None = None,
    backend: Backend = "auto",
    render_mode: RenderMode = "RGB+D+N",
    check_values: bool = True,
) -> RasterResult:
    """Render 3D Gaussians (Kerbl et al., 3D Gaussian Splatting, SIGGRAPH 2023).

    Each Gaussian has covariance :math:`\\Sigma = R S S^T R^T` (:math:`R` from the
    quaternion, :math:`S = \\mathrm{diag}(e^{s})`), is EWA-projected to
    :math:`\\Sigma' = J W \\Sigma W^T J^T + 0.3 I`, binned into the 16x16 tiles its
    3-sigma square touches, sorted by camera z and composited front to back:

    .. math::
        \\alpha_i = \\min\\big(0.99,\\ o_i \\exp(-\\tfrac12 d^T \\Sigma'^{-1}_i d)\\big),\\qquad
        C = \\sum_i c_i \\alpha_i \\prod_{j<i} (1-\\alpha_j) + T_n\\, bg

    skipping :math:`\\alpha_i < 1/255` and stopping before transmittance drops below
    :math:`10^{-4}`. Gaussians nearer than z = 0.01 are culled. Differentiable with respect
    to every Gaussian parameter and the background.

    Args:
        means, quats, log_scales, opacity_logits, colors: Gaussian parameters (shapes above).
            Zero-norm quaternions render as the identity rotation; log-scales are clamped
            to ``[-30, 10]``.
        camera: pinhole camera (OpenCV world-to-camera).
        background: ``[3]`` colour composited behind, or None (black, and no gradient).
        sh_degree: SH degree to evaluate when ``colors`` is ``[N, K, 3]``
            (default: the largest :math:`d` with :math:`(d+1)^2 = K`); the 3DGS
            convention :math:`c = \\max(0, \\mathrm{SH}(v) + 0.5)`.
        backend: ``"numba"`` (fast CPU path), ``"gsplat"`` (CUDA, ``pip install .[cuda]``),
            ``"triton"`` (CUDA: projection, binning and compositing in Triton kernels, which ship
            with torch's CUDA builds; the projection in torch when the camera pose needs a gradient), ``"torch"`` (pure-torch tiled compositor, slow, any
            device), or ``"auto"``: numba for CPU tensors; for CUDA tensors gsplat when it is
            installed, else Triton, else the torch projection on the GPU with the compositing
            on the CPU's numba kernels (said once in a warning: the pure-torch compositor on a
            GPU is many times slower than that); the pure-torch compositor on other devices.
            ``"numba"`` with CUDA tensors asks for that split explicitly. The numba path
            projects in numba too (float64, the formulas of ``project``, with a hand-written
            backward; tests hold both equal to torch autograd of ``project``), except when the
            camera's ``world_to_camera`` needs a gradient (then the projection is torch) and
            for CUDA tensors.
        render_mode: ``"RGB+D+N"`` (colour, depth and normals, what training needs) or
            ``"RGB"`` (colour and alpha alone, ``depth`` and ``normal`` None). On the no-grad
            numba path ``"RGB"`` composites 3 features per pixel instead of 7 (the same colour
            and alpha, bit for bit); the other paths compute all and drop the two.

    Returns:
        A :class:`RasterResult`.

    Raises:
        InputError: bad shapes, non-finite parameters (naming the tensor and how many
            values), or an unavailable backend.
    """
    if render_mode not in RENDER_MODES:
        raise InputError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    degree = check_inputs(means, quats, log_scales, opacity_logits, colors, camera, background, sh_degree,
                          values=check_values)
    chosen = _choose_backend(backend, means.device)
    width, height = int(camera.width), int(camera.height)
    if chosen == "gsplat":
        from lmgs.render._gsplat import rasterize_gsplat

        feat, alpha, means2d, radii = rasterize_gsplat(
            means, quats, log_scales, opacity_logits, colors, degree, camera
        )
        rgb, depth, normal = feat[..., 0:3], feat[..., 3:4], feat[..., 4:7]
    elif chosen == "numba" and means.device.type == "cpu" and not (
            torch.is_grad_enabled() and camera.world_to_camera.requires_grad):
        from lmgs.render._cpu import rasterize_numba

        rgb, depth, normal, alpha, means2d, radii = rasterize_numba(
            means, quats, log_scales, opacity_logits, view_colors(means, colors, degree, camera), camera,
            _MODE_FEATURES[render_mode])
    elif chosen == "triton" and not (torch.is_grad_enabled() and camera.world_to_camera.requires_grad):
        from lmgs.render._triton_projection import rasterize_triton

        rgb, depth, normal, alpha, means2d, radii = rasterize_triton(
            means, quats, log_scales, opacity_logits, view_colors(means, colors, degree, camera), camera)
    else:
        p = project(means, quats, log_scales, opacity_logits, colors, degree, camera)
        if chosen == "numba" and means.device.type != "cpu":
            feat, alpha = _composite_on_cpu(p, width, height)
        else:
            if chosen == "numba":
                from lmgs.render._cpu import composite
            elif chosen == "triton":
                from lmgs.render._triton import composite
            else:
                from lmgs.render._tiled_torch import composite
            feat, alpha = composite(p.means2d, p.conics, p.opacities, p.features, p.radii, p.depths, width, height)
        rgb, depth, normal = feat[..., 0:3], feat[..., 3:4], feat[..., 4:7]
        means2d, radii = p.means2d, p.radii
    if means2d.requires_grad:
        means2d.retain_grad()
    if background is not None:
        rgb = rgb + (1.0 - alpha) * background.to(rgb)
    return RasterResult(
        rgb=rgb,
        alpha=alpha,
        depth=None if render_mode == "RGB" else depth,
        normal=None if render_mode == "RGB" else normal,
        radii=radii,
        visible=radii > 0,
        means2d=means2d,
    )


@functools.lru_cache(maxsize=1)
def gsplat_available() -> bool:
    """True when gsplat imports and its CUDA kernels are there (it is only used on CUDA tensors).

    gsplat builds its kernels on first use (a minute or more, once); without a CUDA toolkit it
    imports but leaves them out (``gsplat.cuda._backend._C is None``), and every call would fail:
    then this is False, with a warning, and ``"auto"`` takes the next path (Triton, else the
    numba compositing on the CPU).
    """
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    try:
        from gsplat.cuda._backend import _C
    except ImportError:  # another layout of gsplat's internals: trust the import
        return True
    if _C is None:
        warnings.warn("gsplat is installed but its CUDA kernels could not be built (no CUDA toolkit found); "
                      "not using it", RuntimeWarning, stacklevel=2)
        return False
    return True


def _composite_on_cpu(p, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite a projection made on another device with the numba kernels, and bring the
    images back (both copies are autograd nodes: the gradients flow back to that device)."""
    from lmgs.render._cpu import composite

    dev = p.means2d.device
    feat, alpha = composite(p.means2d.cpu(), p.conics.cpu(), p.opacities.cpu(), p.features.cpu(), p.radii.cpu(),
                            p.depths.cpu(), width, height)
    return feat.to(dev), alpha.to(dev)


@functools.lru_cache(maxsize=1)
def triton_available() -> bool:
    """True when Triton imports, a CUDA device is there and the kernels compile and run: the
    compositor alone, then projection and compositing together, forward and backward, each tried
    once on a one-Gaussian image (a failure is a warning and False)."""
    if not torch.cuda.is_available():
        return False
    try:
        import triton  # noqa: F401
    except ImportError:
        return False
    try:
        from lmgs.render._triton import composite

        dev = torch.device("cuda")
        with torch.enable_grad():  # the first call may come under no_grad: the backward kernel is tried too
            m2 = torch.tensor([[8.0, 8.0]], device=dev, requires_grad=True)
            feat, alpha = composite(m2, torch.tensor([[0.1, 0.0, 0.1]], device=dev), torch.tensor([0.5], device=dev),
                                    torch.ones(1, 7, device=dev), torch.tensor([4], device=dev),
                                    torch.tensor([1.0], device=dev), 16, 16)
            (feat.sum() + alpha.sum()).backward()
        torch.cuda.synchronize()
        if m2.grad is None or not torch.isfinite(m2.grad).all() or not 0.4 < float(alpha[8, 8, 0]) < 0.6:
            raise RuntimeError(f"one Gaussian of opacity 0.5 composited to alpha {float(alpha[8, 8, 0]):.3f}")
        from lmgs.render._triton_projection import rasterize_triton

        with torch.enable_grad():  # one Gaussian 1 m ahead of a 16x16 camera, opacity 0.5, radius ~1 px * 3
            mean = torch.tensor([[0.0, 0.0, 1.0]], device=dev, requires_grad=True)
            cam = Camera(torch.eye(4, device=dev), 16.0, 16.0, 8.0, 8.0, 16, 16)
            rgb, _, _, alpha, _, _ = rasterize_triton(mean, torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=dev),
                                                      torch.full((1, 3), -2.0, device=dev), torch.zeros(1, device=dev),
                                                      torch.ones(1, 3, device=dev), cam)
            (rgb.sum() + alpha.sum()).backward()
        torch.cuda.synchronize()
        if mean.grad is None or not torch.isfinite(mean.grad).all() or not 0.4 < float(alpha[8, 8, 0]) < 0.6:
            raise RuntimeError(f"one projected Gaussian of opacity 0.5 composited to alpha {float(alpha[8, 8, 0]):.3f}")
    except Exception as e:  # noqa: BLE001 - any compile or launch failure means: not usable here
        warnings.warn(f"Triton is installed but its compositing kernels failed here ({type(e).__name__}: "
                      f"{str(e).splitlines()[0] if str(e) else ''}); not using it", RuntimeWarning, stacklevel=2)
        return False
    return True


@functools.lru_cache(maxsize=1)
def _warn_cpu_compositing() -> None:
    warnings.warn("rasterize: CUDA tensors without gsplat or Triton: projecting on the GPU and compositing on the "
                  "CPU (numba), which is many times faster than the pure-torch compositor on a GPU; install "
                  "triton or 'lmgs[cuda]' for a GPU compositor", RuntimeWarning, stacklevel=4)


def _choose_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise InputError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        if device.type == "cpu":
            return "numba"
        if device.type != "cuda":
            return "torch"
        if gsplat_available():
            return "gsplat"
        if triton_available():
            return "triton"
        _warn_cpu_compositing()
        return "numba"
    if backend == "numba" and device.type not in ("cpu", "cuda"):
        raise InputError(f"backend='numba' needs CPU (or CUDA) tensors, got {device.type}; use 'auto' or 'torch'")
    if backend == "gsplat":
        if device.type != "cuda":
            raise InputError("backend='gsplat' needs CUDA tensors; use 'numba' (or 'auto') on the CPU")
        if not gsplat_available():
            raise InputError("backend='gsplat' needs gsplat with its CUDA kernels: pip install 'lmgs[cuda]', "
                             "and a CUDA toolkit (nvcc) for their build on first use")
    if backend == "triton":
        if device.type != "cuda":
            raise InputError("backend='triton' needs CUDA tensors; use 'numba' (or 'auto') on the CPU")
        if not triton_available():
            raise InputError("backend='triton' needs Triton (it ships with torch's CUDA builds: pip install triton) "
                             "and a CUDA device its kernels compile for")
    return backend
