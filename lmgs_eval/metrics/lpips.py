"""LPIPS (official v0.1, AlexNet) and ST-LPIPS (shift-tolerant AlexNet) through ONNX Runtime.

Both networks are written here in plain torch (no torchvision), loaded from the weight
files on disk, exported once to ONNX (dynamic batch, height and width) into
``cache_root()/onnx/<sha256>-<name>-v<EXPORT_VERSION>.onnx`` and run in onnxruntime.

.. math::
    d(x, y) = \\sum_{l=1}^{5} \\frac{1}{H_l W_l} \\sum_{h,w}
              \\big\\| w_l \\odot (\\hat f^l_{hw}(x) - \\hat f^l_{hw}(y)) \\big\\|_2^2,
    \\qquad \\hat f = f / (\\|f\\|_2 + 10^{-10}) \\text{ over channels}

with inputs in [0, 1] mapped to [-1, 1] and then ``(x - shift) / scale`` (the lpips
``ScalingLayer``). Zhang et al., "The Unreasonable Effectiveness of Deep Features as a
Perceptual Metric", CVPR 2018 (github.com/richzhang/PerceptualSimilarity, lpips 0.1);
Ghildyal & Liu, "Shift-tolerant Perceptual Similarity Metric", ECCV 2022
(github.com/abhijay9/ShiftTolerant-LPIPS, stlpips-pytorch, variant ``shift_tolerant``).

Speed: the ST trunk runs its first 11x11 convolution at stride 1 and then blurs
(binomial [1,2,1]^2/16) and subsamples by 2, all before the ReLU. Convolution followed
by a linear blur-and-subsample is one linear map: a 13x13 convolution at stride 2 with
the composed kernel. That is exact everywhere except the first and last output row and
column, where the blur-pool reflects its input; those are fixed exactly (row 0 equals
row 1 by the symmetry of the reflection; the last row/column come from a 3-row strip
computed the original way). :class:`STAlexTrunk` keeps the unfolded path as its
reference twin (``fold=False``) and the tests hold the two equal.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.base import MetricResult, MetricSpec, check_pair, mean_result

EXPORT_VERSION = "1"
ALEXNET_CKPT = "alexnet-owt-7be5be79.pth"
MIN_SIDE = 32
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)
CHANNELS = (64, 192, 384, 256, 256)

LPIPS_ALEX_SPEC = MetricSpec(
    name="lpips-alex",
    higher_is_better=False,
    unit="",
    backend="onnxruntime",
    version="0.1",
    definition=(
        "LPIPS v0.1, net='alex' (torchvision AlexNet trunk + the lpips v0.1 linear heads), float [0,1] frames "
        "mapped to [-1,1] (normalize=True), full frame, per frame then mean. Run through ONNX Runtime from "
        "a graph the project exports from the weights on disk."
    ),
    reference="Zhang et al. CVPR 2018; lpips 0.1 (richzhang/PerceptualSimilarity)",
)

STLPIPS_ALEX_SPEC = MetricSpec(
    name="stlpips-alex",
    higher_is_better=False,
    unit="",
    backend="onnxruntime",
    version="ST0.0",
    definition=(
        "ST-LPIPS (shift-tolerant LPIPS), AlexNet trunk with stride-1 first conv and blur-pool anti-aliasing "
        "(reflect pad 2, binomial 3x3, stride 2) + five linear heads, weights vST0.0/alex_shift_tolerant.pth "
        "of stlpips-pytorch; float [0,1] frames mapped to [-1,1]; per frame then mean."
    ),
    reference="Ghildyal & Liu, ECCV 2022; stlpips-pytorch 0.0.2 (variant 'shift_tolerant')",
    standin=(
        "ST-LPIPS is NOT the LPIPS papers report: it is the default only because the ImageNet AlexNet "
        f"trunk ({ALEXNET_CKPT}) is not on this machine; values are not comparable with published LPIPS."
    ),
)


# ----------------------------------------------------------------------------- files
def _package_dir(name: str) -> Path | None:
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def lpips_heads_path() -> Path | None:
    """The v0.1 AlexNet linear heads shipped in the ``lpips`` wheel (not imported)."""
    d = _package_dir("lpips")
    p = d / "weights" / "v0.1" / "alex.pth" if d else None
    return p if p is not None and p.is_file() else None


def stlpips_weights_path() -> Path | None:
    """The complete ST-LPIPS AlexNet network shipped in the ``stlpips-pytorch`` wheel."""
    d = _package_dir("stlpips_pytorch")
    p = d / "weights" / "vST0.0" / "alex_shift_tolerant.pth" if d else None
    return p if p is not None and p.is_file() else None


def find_alexnet(explicit: str | os.PathLike | None = None) -> Path | None:
    """torchvision's AlexNet checkpoint: ``explicit``, else the torch hub caches.

    Searched: ``$TORCH_HOME/hub/checkpoints`` and ``~/.cache/torch/hub/checkpoints``.
    Nothing is downloaded.
    """
    if explicit:
        p = Path(explicit).expanduser()
        if not p.is_file():
            raise UserError(f"{p}: AlexNet checkpoint not found (--alexnet)")
        return p
    roots = []
    if os.environ.get("TORCH_HOME"):
        roots.append(Path(os.environ["TORCH_HOME"]).expanduser())
    roots.append(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "torch")
    roots.append(Path.home() / ".cache" / "torch")
    for r in roots:
        p = r / "hub" / "checkpoints" / ALEXNET_CKPT
        if p.is_file():
            return p
    return None


# ----------------------------------------------------------------------------- networks
def _torch():
    import torch

    return torch


def _build_modules():
    """Define the torch modules lazily (torch is a heavy import)."""
    torch = _torch()
    import torch.nn.functional as F
    from torch import nn

    class AlexTrunk(nn.Module):
        """torchvision AlexNet ``features`` up to relu5 (the official LPIPS trunk).

        conv 3-64 k11 s4 p2, ReLU | maxpool 3/2, conv 64-192 k5 p2, ReLU | maxpool 3/2,
        conv 192-384 k3 p1, ReLU | conv 384-256 k3 p1, ReLU | conv 256-256 k3 p1, ReLU.
        Keys in torchvision's layout: ``features.{0,3,6,8,10}.{weight,bias}``.
        """

        def __init__(self):
            super().__init__()
            self.c1 = nn.Conv2d(3, 64, 11, stride=4, padding=2)
            self.c2 = nn.Conv2d(64, 192, 5, padding=2)
            self.c3 = nn.Conv2d(192, 384, 3, padding=1)
            self.c4 = nn.Conv2d(384, 256, 3, padding=1)
            self.c5 = nn.Conv2d(256, 256, 3, padding=1)

        def load_torchvision(self, sd: dict) -> None:
            mapping = {"c1": "features.0", "c2": "features.3", "c3": "features.6", "c4": "features.8", "c5": "features.10"}
            own = {}
            for mine, theirs in mapping.items():
                for p in ("weight", "bias"):
                    key = f"{theirs}.{p}"
                    if key not in sd:
                        raise UserError(f"AlexNet checkpoint: missing key {key!r} (expected torchvision's alexnet layout)")
                    own[f"{mine}.{p}"] = sd[key]
            self.load_state_dict(own)

        def forward(self, x):
            h1 = F.relu(self.c1(x))
            h2 = F.relu(self.c2(F.max_pool2d(h1, 3, 2)))
            h3 = F.relu(self.c3(F.max_pool2d(h2, 3, 2)))
            h4 = F.relu(self.c4(h3))
            h5 = F.relu(self.c5(h4))
            return h1, h2, h3, h4, h5

    class STAlexTrunk(nn.Module):
        """The shift-tolerant AlexNet trunk of ST-LPIPS (``variant='shift_tolerant'``).

        slice1: conv 3-64 k11 s1 p2, blurpool | slice2: ReLU... precisely, following
        ``stlpips_pytorch/invariant_networks.py``::

            relu1 = ReLU(BP(conv1(x)))
            relu2 = ReLU(conv2(BP(maxpool_3s1(relu1))))
            relu3 = ReLU(conv3(BP(maxpool_3s1(relu2))))
            relu4 = ReLU(conv4(relu3));  relu5 = ReLU(conv5(relu4))

        where BP = reflect pad 2 on every side, then depthwise binomial 3x3 at stride 2.
        ``fold=True`` computes ``BP(conv1(x))`` as one stride-2 13x13 convolution plus
        exact border fix-ups (see the module docstring).
        """

        def __init__(self, fold: bool = True):
            super().__init__()
            self.fold = fold
            self.c1 = nn.Conv2d(3, 64, 11, stride=1, padding=2)
            self.c2 = nn.Conv2d(64, 192, 5, padding=2)
            self.c3 = nn.Conv2d(192, 384, 3, padding=1)
            self.c4 = nn.Conv2d(384, 256, 3, padding=1)
            self.c5 = nn.Conv2d(256, 256, 3, padding=1)
            self.register_buffer("f1", torch.tensor([0.25, 0.5, 0.25]))  # binomial [1,2,1]/4
            self.register_buffer("k13", torch.zeros(64, 3, 13, 13))
            self.register_buffer("w_odd", torch.tensor([0.25, 0.5, 0.25]))
            self.register_buffer("w_even", torch.tensor([0.0, 0.5, 0.5]))

        def load_stlpips(self, sd: dict) -> None:
            mapping = {"c1": "net.slice1.0", "c2": "net.slice2.5", "c3": "net.slice3.9", "c4": "net.slice4.11", "c5": "net.slice5.13"}
            own = {}
            for mine, theirs in mapping.items():
                for p in ("weight", "bias"):
                    key = f"{theirs}.{p}"
                    if key not in sd:
                        raise UserError(f"ST-LPIPS weights: missing key {key!r}")
                    own[f"{mine}.{p}"] = sd[key]
            for key in ("net.slice1.1.filt", "net.slice2.4.filt", "net.slice3.8.filt"):
                filt = sd.get(key)
                expect = torch.outer(self.f1, self.f1)
                if filt is None or not torch.allclose(filt[:, 0].float(), expect.expand_as(filt[:, 0]), atol=1e-7):
                    raise UserError(f"ST-LPIPS weights: {key} is not the binomial 3x3 blur this port assumes")
            own["f1"] = self.f1
            own["k13"] = self.k13
            own["w_odd"], own["w_even"] = self.w_odd, self.w_even
            self.load_state_dict(own)
            self.refresh_fold()

        @torch.no_grad()
        def refresh_fold(self) -> None:
            """Compose conv1 (11x11) with the 3x3 blur into the 13x13 stride-2 kernel."""
            w = self.c1.weight.detach()
            f2 = torch.outer(self.f1, self.f1).flip(0, 1).view(1, 1, 3, 3).to(w.dtype)
            k = F.conv2d(F.pad(w.reshape(-1, 1, 11, 11), (2, 2, 2, 2)), f2)
            self.k13.copy_(k.reshape(64, 3, 13, 13))

        def _bp(self, x, c: int):
            filt = torch.outer(self.f1, self.f1).expand(c, 1, 3, 3)
            return F.conv2d(F.pad(x, (2, 2, 2, 2), mode="reflect"), filt, stride=2, groups=c)

        def _bp1d(self, x, dim: int, c: int = 64):
            """Blur-pool along one axis only (dim 2 = rows, 3 = columns); ``c`` channels.

            Channel counts are Python constants so the exported kernels have static shapes.
            """
            if dim == 2:
                return F.conv2d(F.pad(x, (0, 0, 2, 2), mode="reflect"), self.f1.view(1, 1, 3, 1).expand(c, 1, 3, 1),
                                stride=(2, 1), groups=c)
            return F.conv2d(F.pad(x, (2, 2, 0, 0), mode="reflect"), self.f1.view(1, 1, 1, 3).expand(c, 1, 1, 3),
                            stride=(1, 2), groups=c)

        def _edge_weights(self, n_along):
            """Weights of the last 3 conv1 rows in the last blur-pooled row.

            For n conv1 rows the reflect-padded sequence ends ``y[n-3], y[n-2], y[n-1],
            y[n-2], y[n-3]``; the last stride-2 window starts at an even index, so it is
            ``(y[n-3] + 2y[n-2] + y[n-1])/4`` for odd n and ``(2y[n-2] + 2y[n-1])/4``
            for even n. ``n_along`` is a 1-D tensor of length n, so the parity stays a
            graph computation under dynamic ONNX shapes.
            """
            n = torch.ones_like(n_along).sum()
            p = torch.remainder(n, 2.0)
            return p * self.w_odd + (1.0 - p) * self.w_even

        def _bp_conv1(self, x):
            if not self.fold:
                return self._bp(self.c1(x), 64)
            b = self.c1.bias
            zs = F.conv2d(F.pad(x, (4, 4, 4, 4)), self.k13, b, stride=2)  # interior, exact
            xp2 = F.pad(x, (2, 2, 2, 2))
            # last 3 conv1 rows (full width), blurred along columns exactly
            ybot = self._bp1d(F.conv2d(xp2[:, :, -13:, :], self.c1.weight, b), 3)  # [N,64,3,Wo]
            # last 3 conv1 columns (full height), blurred along rows exactly
            yrgt = self._bp1d(F.conv2d(xp2[:, :, :, -13:], self.c1.weight, b), 2)  # [N,64,Ho,3]
            wr = self._edge_weights(x[0, 0, 6:, 0])  # conv1 output has H - 6 rows
            wc = self._edge_weights(x[0, 0, 0, 6:])
            last_row = (ybot * wr.view(1, 1, 3, 1)).sum(dim=2, keepdim=True)
            last_col = (yrgt * wc.view(1, 1, 1, 3)).sum(dim=3, keepdim=True)
            z = torch.cat([zs[:, :, :-1, :], last_row], dim=2)
            z = torch.cat([z[:, :, :, :-1], last_col], dim=3)
            z = torch.cat([z[:, :, :, 1:2], z[:, :, :, 1:]], dim=3)  # column 0 == column 1
            return torch.cat([z[:, :, 1:2, :], z[:, :, 1:, :]], dim=2)  # row 0 == row 1

        def forward(self, x):
            h1 = F.relu(self._bp_conv1(x))
            h2 = F.relu(self.c2(self._bp(F.max_pool2d(h1, 3, 1), 64)))
            h3 = F.relu(self.c3(self._bp(F.max_pool2d(h2, 3, 1), 192)))
            h4 = F.relu(self.c4(h3))
            h5 = F.relu(self.c5(h4))
            return h1, h2, h3, h4, h5

    class LPIPSNet(nn.Module):
        """``forward(pred, gt) -> [N]`` LPIPS distances of [0, 1] images ``[N, 3, H, W]``."""

        def __init__(self, trunk: nn.Module):
            super().__init__()
            self.trunk = trunk
            self.register_buffer("shift", torch.tensor(LPIPS_SHIFT).view(1, 3, 1, 1))
            self.register_buffer("scale", torch.tensor(LPIPS_SCALE).view(1, 3, 1, 1))
            self.lins = nn.ModuleList([nn.Conv2d(c, 1, 1, bias=False) for c in CHANNELS])

        def load_heads(self, sd: dict, prefix: str = "") -> None:
            for i, lin in enumerate(self.lins):
                key = f"{prefix}lin{i}.model.1.weight"
                if key not in sd:
                    raise UserError(f"LPIPS heads: missing key {key!r}")
                lin.weight.data.copy_(sd[key].reshape(lin.weight.shape))

        def forward(self, pred, gt):
            n = pred.shape[0]
            x = torch.cat([pred, gt], dim=0) * 2.0 - 1.0  # one trunk pass for both images
            x = (x - self.shift) / self.scale
            total = None
            for lin, f in zip(self.lins, self.trunk(x)):
                f = f / (torch.sqrt(torch.sum(f * f, dim=1, keepdim=True)) + 1e-10)
                d = (f[:n] - f[n:]) ** 2
                v = lin(d).mean(dim=(2, 3))[:, 0]
                total = v if total is None else total + v
            return total

    return AlexTrunk, STAlexTrunk, LPIPSNet


_MODULES = None


def modules():
    """``(AlexTrunk, STAlexTrunk, LPIPSNet)`` classes (built on first use)."""
    global _MODULES
    if _MODULES is None:
        _MODULES = _build_modules()
    return _MODULES


def build_stlpips_torch(weights: Path | None = None, fold: bool = True):
    """The ST-LPIPS network in eager torch (eval mode), and the sha256 of its weights."""
    from lmgs_eval.metrics.ort import load_torch_state, sha256_file

    weights = weights or stlpips_weights_path()
    if weights is None:
        raise UserError("stlpips-pytorch is not installed: its weights vST0.0/alex_shift_tolerant.pth are needed")
    sd = load_torch_state(weights, "ST-LPIPS weights")
    _, ST, Net = modules()
    net = Net(ST(fold=fold))
    net.trunk.load_stlpips(sd)
    net.load_heads(sd)
    for k in ("scaling_layer.shift", "scaling_layer.scale"):
        if k in sd:
            getattr(net, k.split(".")[1]).copy_(sd[k].reshape(1, 3, 1, 1))
    return net.eval(), sha256_file(weights)


def build_lpips_alex_torch(alexnet: Path, heads: Path | None = None):
    """Official LPIPS v0.1 alex in eager torch, and a sha256 over both weight files."""
    from lmgs_eval.metrics.ort import load_torch_state, sha256_file

    heads = heads or lpips_heads_path()
    if heads is None:
        raise UserError("the lpips wheel (its weights/v0.1/alex.pth) is not installed: pip install --no-deps lpips")
    Alex, _, Net = modules()
    net = Net(Alex())
    net.trunk.load_torchvision(load_torch_state(alexnet, "AlexNet checkpoint"))
    net.load_heads(load_torch_state(heads, "LPIPS heads"))
    sha = hashlib.sha256((sha256_file(alexnet) + sha256_file(heads)).encode()).hexdigest()
    return net.eval(), sha


# ----------------------------------------------------------------------------- ONNX
def onnx_path(name: str, sha: str) -> Path:
    from lmgs_eval.metrics.ort import onnx_cache_dir

    return onnx_cache_dir() / f"{sha}-{name}-v{EXPORT_VERSION}.onnx"


def export_lpips(net, path: Path) -> None:
    from lmgs_eval.metrics.ort import export_onnx

    torch = _torch()
    dummy = torch.rand(1, 3, 64, 64)
    axes = {0: "n", 2: "h", 3: "w"}
    export_onnx(net, (dummy, dummy.clone()), path, ["pred", "gt"], ["dist"],
                {"pred": axes, "gt": axes, "dist": {0: "n"}})


def lpips_session(net, name: str, sha: str, threads: int | None = None):
    """Load (or export once, then load) the cached ONNX graph of ``net``."""
    from lmgs_eval.metrics.ort import load_session

    path = onnx_path(name, sha)
    if not path.is_file():
        export_lpips(net, path)
    try:
        return load_session(path, threads), path
    except UserError:
        path.unlink(missing_ok=True)  # a damaged cache entry is rebuilt once, from the weights
        export_lpips(net, path)
        return load_session(path, threads), path


# ----------------------------------------------------------------------------- metric
@dataclass
class LPIPSBackend:
    """Resolved LPIPS network: which one, its spec (with sha256) and how it runs."""

    spec: MetricSpec
    net: object  # eager torch twin (kept for tests and the benchmark)
    session: object | None
    onnx_file: Path | None


def resolve_lpips(name: str | None = None, alexnet: str | os.PathLike | None = None,
                  use_onnx: bool = True, threads: int | None = None) -> LPIPSBackend:
    """Pick the LPIPS network: official ``lpips-alex`` when the trunk is present, else ST-LPIPS.

    Args:
        name: ``"lpips-alex"``, ``"stlpips-alex"`` or ``None`` (official when available).
        alexnet: explicit path of ``alexnet-owt-7be5be79.pth``.
        use_onnx: build the ONNX Runtime session (else eager torch only).
        threads: intra-op threads (default: all cores of this process).
    """
    trunk = find_alexnet(alexnet)
    if name is None:
        name = "lpips-alex" if trunk is not None else "stlpips-alex"
    if name == "lpips-alex":
        if trunk is None:
            raise UserError(f"lpips-alex needs torchvision's {ALEXNET_CKPT} in the torch hub cache or --alexnet PATH")
        net, sha = build_lpips_alex_torch(trunk)
        spec = LPIPS_ALEX_SPEC
    elif name == "stlpips-alex":
        net, sha = build_stlpips_torch()
        spec = STLPIPS_ALEX_SPEC
    else:
        raise UserError(f"unknown LPIPS network {name!r}")
    sess, path = lpips_session(net, name, sha, threads) if use_onnx else (None, None)
    return LPIPSBackend(spec.with_weights(sha, "onnxruntime" if use_onnx else "torch"), net, sess, path)


class LPIPS:
    """LPIPS metric over frames, batched through ONNX Runtime (or eager torch).

    Args:
        name: see :func:`resolve_lpips`.
        batch: frame pairs per run (bounds memory: about 0.25 GB per pair at 512x512 for ST).
    """

    def __init__(self, name: str | None = None, alexnet=None, use_onnx: bool = True, batch: int = 4,
                 threads: int | None = None):
        self.backend = resolve_lpips(name, alexnet, use_onnx, threads)
        self.spec = self.backend.spec
        self.batch = int(batch)

    def distances(self, pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
        """Per-frame distances of ``[T, H, W, 3]`` float frames in [0, 1]."""
        pred, gt = check_pair(pred, gt)
        t, h, w, _ = pred.shape
        if h < MIN_SIDE or w < MIN_SIDE:
            raise UserError(f"{self.spec.name}: frames must be at least {MIN_SIDE}x{MIN_SIDE}, got {h}x{w}")
        out = np.empty(t, np.float64)
        for s in range(0, t, self.batch):
            p = np.ascontiguousarray(pred[s:s + self.batch].transpose(0, 3, 1, 2), np.float32)
            g = np.ascontiguousarray(gt[s:s + self.batch].transpose(0, 3, 1, 2), np.float32)
            if self.backend.session is not None:
                d = self.backend.session.run(["dist"], {"pred": p, "gt": g})[0]
            else:
                torch = _torch()
                with torch.no_grad():
                    d = self.backend.net(torch.from_numpy(p), torch.from_numpy(g)).numpy()
            out[s:s + p.shape[0]] = d
        return out

    def update(self, pred: np.ndarray, gt: np.ndarray) -> dict[str, np.ndarray]:
        return {"per_item": self.distances(pred, gt)}

    def compute(self, stats: dict[str, np.ndarray]) -> MetricResult:
        r = mean_result(self.spec, stats["per_item"], [])
        if self.spec.standin:
            r.notes.append("standin: " + self.spec.standin)
        r.notes.append("frames scored as float32 [0,1] (not re-encoded)")
        return r
