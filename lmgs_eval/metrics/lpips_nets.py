"""The LPIPS networks in plain torch (no torchvision): the AlexNet trunk of the official LPIPS v0.1,
the shift-tolerant trunk of ST-LPIPS (with its folded fast path and the unfolded reference twin),
and the network that compares their normalised features through the learned linear heads.
How the weights are found, exported to ONNX and scored is in :mod:`lmgs_eval.metrics.lpips`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from lmgs_eval.errors import UserError

LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)
CHANNELS = (64, 192, 384, 256, 256)


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

    MAPPING = {"c1": "features.0", "c2": "features.3", "c3": "features.6", "c4": "features.8", "c5": "features.10"}
    CLASSIFIER = ("classifier.1", "classifier.4", "classifier.6")
    """torchvision's AlexNet classifier layers: in its checkpoint, unused by LPIPS (any shape, or absent)."""

    def torchvision_shapes(self) -> dict[str, tuple[int, ...]]:
        """The trunk's keys in torchvision's layout and the shape each must have."""
        return {f"{theirs}.{p}": tuple(getattr(getattr(self, mine), p).shape)
                for mine, theirs in self.MAPPING.items() for p in ("weight", "bias")}

    def load_torchvision(self, sd: dict, source: str = "AlexNet checkpoint") -> None:
        """Load ``features.*`` of a torchvision AlexNet state dict.

        Raises:
            UserError: one line naming ``source`` and the first torchvision key at fault: keys
                missing, keys that are not torchvision's AlexNet's, or a tensor of the wrong shape.
        """
        want = self.torchvision_shapes()
        allowed = set(want) | {f"{k}.{p}" for k in self.CLASSIFIER for p in ("weight", "bias")}
        missing = [k for k in want if k not in sd]
        extra = sorted(k for k in sd if k not in allowed)
        if missing or extra:
            parts = ([f"missing {_keys(missing)}"] if missing else []) + ([f"unexpected {_keys(extra)}"] if extra else [])
            raise UserError(f"{source}: not torchvision's alexnet layout: {'; '.join(parts)}")
        for key, shape in want.items():
            got = tuple(sd[key].shape)
            if got != shape:
                raise UserError(f"{source}: {key}: expected shape {shape}, got {got}")
        own = {f"{mine}.{p}": sd[f"{theirs}.{p}"] for mine, theirs in self.MAPPING.items() for p in ("weight", "bias")}
        self.load_state_dict(own)

    def forward(self, x):
        h1 = F.relu(self.c1(x))
        h2 = F.relu(self.c2(F.max_pool2d(h1, 3, 2)))
        h3 = F.relu(self.c3(F.max_pool2d(h2, 3, 2)))
        h4 = F.relu(self.c4(h3))
        h5 = F.relu(self.c5(h4))
        return h1, h2, h3, h4, h5


def _keys(keys: list[str], show: int = 4) -> str:
    """``'a', 'b' and 3 more``: a key list short enough for one line."""
    head = ", ".join(repr(k) for k in keys[:show])
    return head + (f" and {len(keys) - show} more" if len(keys) > show else "")


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
            if sd[key].numel() != lin.weight.numel():
                raise UserError(f"LPIPS heads: {key}: expected {lin.weight.numel()} values "
                                f"(shape {tuple(lin.weight.shape)}), got shape {tuple(sd[key].shape)}")
            lin.weight.data.copy_(sd[key].reshape(lin.weight.shape))

    def features(self, x):
        """The five channel-normalised feature maps of [0, 1] images ``[N, 3, H, W]``."""
        x = (x * 2.0 - 1.0 - self.shift) / self.scale
        return tuple(f / (torch.sqrt(torch.sum(f * f, dim=1, keepdim=True)) + 1e-10) for f in self.trunk(x))

    def head_weights(self) -> list:
        """The linear heads' channel weights, one ``[C_l]`` tensor per layer."""
        return [lin.weight.detach().reshape(-1) for lin in self.lins]

    def forward(self, pred, gt):
        n = pred.shape[0]
        feats = self.features(torch.cat([pred, gt], dim=0))  # one trunk pass for both images
        total = None
        for lin, f in zip(self.lins, feats):
            d = (f[:n] - f[n:]) ** 2
            v = lin(d).mean(dim=(2, 3))[:, 0]
            total = v if total is None else total + v
        return total


class FeatureGraph(nn.Module):
    """``forward(x) -> (f1..f5)``: the exported half of LPIPS (its trunk and normalisation).

    The distance itself (a weighted sum of squared differences) is computed outside the graph,
    so one image's features can be reused against many others (a ground truth scored once).
    """

    def __init__(self, net: LPIPSNet):
        super().__init__()
        self.net = net

    def forward(self, x):
        return self.net.features(x)
