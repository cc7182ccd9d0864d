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
import torch

from lmgs_eval.metrics.base import MetricResult, MetricSpec, check_pair, mean_result
from lmgs_eval.metrics.lpips_nets import AlexTrunk, LPIPSNet, STAlexTrunk
from lmgs_eval.metrics.ort import export_onnx, load_session, load_torch_state, onnx_cache_dir, sha256_file

EXPORT_VERSION = "1"
ALEXNET_CKPT = "alexnet-owt-7be5be79.pth"
ALEXNET_SHA256_PREFIX = "7be5be79"
"""torchvision's published AlexNet trunk: its sha256 starts with these 8 hex digits, which torch hub
puts in the file name and checks on download (``torch.hub.download_url_to_file(..., hash_prefix=...)``).
A trunk whose sha256 does not start with them scores as ``lpips-alex-custom``, whatever its name."""
LPIPS_HEADS_SHA256 = "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0"
"""sha256 of ``lpips/weights/v0.1/alex.pth``, the LPIPS v0.1 linear heads (the same file in the lpips
0.1.2, 0.1.3 and 0.1.4 wheels on PyPI)."""
MIN_SIDE = 32
ALEX_NAMES = ("lpips-alex", "lpips-alex-custom")
"""The LPIPS v0.1 alex network: official with torchvision's trunk, custom with any other AlexNet-shaped one."""


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

LPIPS_ALEX_CUSTOM_SPEC = MetricSpec(
    name="lpips-alex-custom",
    higher_is_better=False,
    unit="",
    backend="onnxruntime",
    version="0.1",
    definition=(
        "The LPIPS v0.1 alex network (the lpips v0.1 linear heads, inputs and averaging as lpips-alex) on an "
        "AlexNet-shaped trunk that is not torchvision's published one: the trunk file's sha256 does not start "
        f"with {ALEXNET_SHA256_PREFIX}. The trunk's path and sha256 are recorded with the value."
    ),
    reference="Zhang et al. CVPR 2018; lpips 0.1 (richzhang/PerceptualSimilarity), with a trunk of the user's",
    standin=(
        "an AlexNet-shaped trunk that is not torchvision's published alexnet-owt-7be5be79.pth (its sha256 does "
        f"not start with {ALEXNET_SHA256_PREFIX}); values are not comparable with published LPIPS."
    ),
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
def build_stlpips_torch(weights: Path | None = None, fold: bool = True):
    """The ST-LPIPS network in eager torch (eval mode), and the sha256 of its weights."""
    weights = weights or stlpips_weights_path()
    if weights is None:
        raise UserError("stlpips-pytorch is not installed: its weights vST0.0/alex_shift_tolerant.pth are needed")
    sd = load_torch_state(weights, "ST-LPIPS weights")
    ST, Net = STAlexTrunk, LPIPSNet
    net = Net(ST(fold=fold))
    net.trunk.load_stlpips(sd)
    net.load_heads(sd)
    for k in ("scaling_layer.shift", "scaling_layer.scale"):
        if k in sd:
            getattr(net, k.split(".")[1]).copy_(sd[k].reshape(1, 3, 1, 1))
    return net.eval(), sha256_file(weights)


def is_official_alexnet(sha256: str) -> bool:
    """Whether a trunk file of this sha256 is torchvision's published AlexNet (:data:`ALEXNET_SHA256_PREFIX`)."""
    return sha256.startswith(ALEXNET_SHA256_PREFIX)


def check_heads(heads: Path) -> str:
    """The sha256 of the LPIPS heads file, which must be the published v0.1 heads.

    Raises:
        UserError: any other file (one line, both hashes).
    """
    sha = sha256_file(heads)
    if sha != LPIPS_HEADS_SHA256:
        raise UserError(f"{heads}: sha256 {sha[:16]}... is not the lpips v0.1 alex heads' ({LPIPS_HEADS_SHA256[:16]}...); "
                        "reinstall the lpips wheel: pip install --force-reinstall --no-deps lpips")
    return sha


@dataclass(frozen=True)
class AlexWeights:
    """The two files of LPIPS alex, their hashes, and the name their numbers go under."""

    trunk: Path
    trunk_sha256: str
    heads: Path
    heads_sha256: str

    @property
    def official(self) -> bool:
        return is_official_alexnet(self.trunk_sha256)

    @property
    def name(self) -> str:
        """``lpips-alex`` for torchvision's published trunk, else ``lpips-alex-custom``."""
        return "lpips-alex" if self.official else "lpips-alex-custom"

    @property
    def sha256(self) -> str:
        """The hash over both files (the ``weights_sha256`` of the result)."""
        return hashlib.sha256((self.trunk_sha256 + self.heads_sha256).encode()).hexdigest()

    @property
    def files(self) -> tuple[tuple[str, str, str], ...]:
        return (("alexnet", str(self.trunk.resolve()), self.trunk_sha256),
                ("lpips_heads", str(self.heads.resolve()), self.heads_sha256))


def alex_weights(alexnet: Path, heads: Path | None = None) -> AlexWeights:
    """Hash the trunk and the heads (the heads must be the published v0.1 file)."""
    heads = heads or lpips_heads_path()
    if heads is None:
        raise UserError("the lpips wheel (its weights/v0.1/alex.pth) is not installed: pip install --no-deps lpips")
    alexnet = Path(alexnet)
    if not alexnet.is_file():
        raise UserError(f"{alexnet}: AlexNet checkpoint not found")
    return AlexWeights(alexnet, sha256_file(alexnet), Path(heads), check_heads(Path(heads)))


def custom_trunk_line(path: str | os.PathLike, sha256: str) -> str:
    """One line saying that LPIPS on this trunk (not torchvision's) is scored as ``lpips-alex-custom``."""
    return (f"{path}: sha256 {sha256[:8]}... is not torchvision's published AlexNet ({ALEXNET_SHA256_PREFIX}...): "
            "LPIPS scored as lpips-alex-custom, not comparable with published LPIPS")


def build_lpips_alex_torch(alexnet: Path, heads: Path | None = None, weights: AlexWeights | None = None):
    """LPIPS v0.1 alex in eager torch, and its :class:`AlexWeights` (hashes, official or custom)."""
    w = weights or alex_weights(alexnet, heads)
    Alex, Net = AlexTrunk, LPIPSNet
    net = Net(Alex())
    net.trunk.load_torchvision(load_torch_state(w.trunk, "AlexNet checkpoint"), f"{w.trunk}")
    net.load_heads(load_torch_state(w.heads, "LPIPS heads"))
    return net.eval(), w


# ----------------------------------------------------------------------------- ONNX
def onnx_path(name: str, sha: str) -> Path:
    return onnx_cache_dir() / f"{sha}-{name}-v{EXPORT_VERSION}.onnx"


def export_lpips(net, path: Path) -> None:
    dummy = torch.rand(1, 3, 64, 64)
    axes = {0: "n", 2: "h", 3: "w"}
    export_onnx(net, (dummy, dummy.clone()), path, ["pred", "gt"], ["dist"],
                {"pred": axes, "gt": axes, "dist": {0: "n"}})


def lpips_session(net, name: str, sha: str, threads: int | None = None):
    """Load (or export once, then load) the cached ONNX graph of ``net``."""
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
    """Pick the LPIPS network: LPIPS alex when a trunk is present, else ST-LPIPS.

    The alex network's name is decided by the trunk's sha256, not by what was asked for or by the
    file's name: ``lpips-alex`` when it is torchvision's published trunk (:func:`is_official_alexnet`),
    else ``lpips-alex-custom`` (its own spec, a labelled stand-in).

    Args:
        name: ``"lpips-alex"``, ``"lpips-alex-custom"``, ``"stlpips-alex"`` or ``None`` (alex when a
            trunk is found).
        alexnet: explicit path of the AlexNet trunk (torchvision's ``alexnet-owt-7be5be79.pth``).
        use_onnx: build the ONNX Runtime session (else eager torch only).
        threads: intra-op threads (default: all cores of this process).
    """
    trunk = find_alexnet(alexnet)
    if name is None:
        name = "lpips-alex" if trunk is not None else "stlpips-alex"
    files: tuple = ()
    if name in ALEX_NAMES:
        if trunk is None:
            raise UserError(f"{name} needs torchvision's {ALEXNET_CKPT} in the torch hub cache or --alexnet PATH")
        net, w = build_lpips_alex_torch(trunk)
        spec = LPIPS_ALEX_SPEC if w.official else LPIPS_ALEX_CUSTOM_SPEC
        sha, files = w.sha256, w.files
    elif name == "stlpips-alex":
        net, sha = build_stlpips_torch()
        spec = STLPIPS_ALEX_SPEC
    else:
        raise UserError(f"unknown LPIPS network {name!r}")
    sess, path = lpips_session(net, spec.name, sha, threads) if use_onnx else (None, None)
    return LPIPSBackend(spec.with_weights(sha, "onnxruntime" if use_onnx else "torch", files), net, sess, path)


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
