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
from lmgs_eval.metrics.lpips_nets import AlexTrunk, FeatureGraph, LPIPSNet, STAlexTrunk
from lmgs.fileio import sha256_file
from lmgs_eval.metrics.ort import export_onnx, load_session, load_torch_state, onnx_cache_dir

EXPORT_VERSION = "2"  # 2: the graph is the feature half; distances are computed outside it
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
    """Export the feature half of ``net`` (:class:`FeatureGraph`): ``x -> f1..f5``, dynamic batch and size."""
    dummy = torch.rand(2, 3, 64, 64)
    axes = {0: "n", 2: "h", 3: "w"}
    outs = [f"f{i}" for i in range(1, 6)]
    export_onnx(FeatureGraph(net).eval(), (dummy,), path, ["x"], outs, {"x": axes, **{o: axes for o in outs}})


def lpips_session(net, name: str, sha: str, threads: int | None = None, path: Path | None = None):
    """Load (or export once, then load) the cached ONNX feature graph of ``net`` (at ``path`` when given)."""
    path = path or onnx_path(name, sha)
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
    return backend_of(net, spec, spec.name, sha, use_onnx, threads, files=files)


def backend_of(net, spec: MetricSpec, name: str, sha: str | None, use_onnx: bool = True, threads: int | None = None,
               path: Path | None = None, files: tuple = ()) -> LPIPSBackend:
    """An :class:`LPIPSBackend` for a built network (exports and loads its feature graph when ``use_onnx``)."""
    sess, path = lpips_session(net, name, sha, threads, path) if use_onnx else (None, None)
    return LPIPSBackend(spec.with_weights(sha, "onnxruntime" if use_onnx else "torch", files), net, sess, path)


def default_cache_budget() -> int:
    """Bytes the ground-truth feature cache may hold: ``$LMGS_GT_CACHE_GB``, else 40 % of free memory, at most 8 GiB."""
    env = os.environ.get("LMGS_GT_CACHE_GB")
    if env:
        try:
            return int(float(env) * 2**30)
        except ValueError:
            raise UserError(f"LMGS_GT_CACHE_GB={env!r}: expected a number of GiB") from None
    try:
        free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        free = 4 * 2**30
    return int(min(8 * 2**30, 0.4 * free))


class LPIPS:
    """LPIPS metric over frames, batched through ONNX Runtime (or eager torch).

    The network runs as its feature half (trunk and channel normalisation, :func:`export_lpips`);
    the distance, a weighted sum of squared feature differences averaged over each layer's pixels,
    is computed here in float32. So a ground truth's features can be kept and reused: with
    ``gt_key`` (a digest of the ground-truth frames) they are computed once and held, as many
    frames as fit in ``cache_bytes`` (about 10 MB per 512x512 frame for the official network,
    45 MB for ST-LPIPS); frames beyond the budget are recomputed per call, and the result says so.

    Args:
        name: see :func:`resolve_lpips`.
        batch: frames per run (bounds the working memory).
        cache_bytes: the ground-truth cache's budget (default :func:`default_cache_budget`).
    """

    def __init__(self, name: str | None = None, alexnet=None, use_onnx: bool = True, batch: int = 4,
                 threads: int | None = None, cache_bytes: int | None = None, backend: LPIPSBackend | None = None):
        self.backend = backend or resolve_lpips(name, alexnet, use_onnx, threads)
        self.spec = self.backend.spec
        self.batch = int(batch)
        self.cache_bytes = default_cache_budget() if cache_bytes is None else int(cache_bytes)
        self._heads = [w.numpy().astype(np.float32) for w in self.backend.net.head_weights()]
        self._gt_key: str | None = None
        self._gt_feats: list | None = None
        self.cache_note = ""

    def features(self, x: np.ndarray) -> list[np.ndarray]:
        """Normalised features of ``[N, H, W, 3]`` frames (float in [0, 1], or uint8 converted here): five
        ``[N, C, h, w]`` float32 arrays."""
        if x.dtype == np.uint8:
            x = x.astype(np.float32) / 255.0
        x = np.ascontiguousarray(x.transpose(0, 3, 1, 2), np.float32)
        if self.backend.session is not None:
            return self.backend.session.run(None, {"x": x})
        with torch.no_grad():
            return [f.numpy() for f in self.backend.net.features(torch.from_numpy(x))]

    def distance(self, fp: list[np.ndarray], fg: list[np.ndarray]) -> np.ndarray:
        """Per-image LPIPS of two feature lists (``fg`` of batch 1 broadcasts)."""
        total = np.zeros(fp[0].shape[0], np.float64)
        for w, a, b in zip(self._heads, fp, fg):
            d = a - b
            d *= d
            total += np.tensordot(d, w, axes=([1], [0])).mean(axis=(1, 2), dtype=np.float64)
        return total

    def distances(self, pred: np.ndarray, gt: np.ndarray, gt_key: str | None = None, same: bool = False) -> np.ndarray:
        """Per-frame distances of ``[T, H, W, 3]`` frames: float in [0, 1], or both uint8 (converted a batch at a
        time, the same numbers as dividing the whole clips by 255 first).

        Args:
            gt_key: a digest of ``gt`` (content, not identity): its features are kept for the next call with the
                same key while they fit the cache budget.
            same: ``pred`` is ``gt`` (the ground truth scored as a method): distances are 0 and only the
                ground truth's features are computed (to fill the cache).
        """
        if pred.dtype == np.uint8 and gt.dtype == np.uint8:
            if pred.ndim != 4 or pred.shape[-1] != 3 or pred.shape != gt.shape:
                raise UserError(f"pred and gt must be [T, H, W, 3] of one shape: {tuple(pred.shape)} vs {tuple(gt.shape)}")
        else:
            pred, gt = check_pair(pred, gt)
        t, h, w, _ = pred.shape
        if h < MIN_SIDE or w < MIN_SIDE:
            raise UserError(f"{self.spec.name}: frames must be at least {MIN_SIDE}x{MIN_SIDE}, got {h}x{w}")
        cached = self._gt_feats if (gt_key is not None and gt_key == self._gt_key) else []
        building = gt_key is not None and gt_key != self._gt_key
        if gt_key is None:
            self.cache_note = ""
        keep: list = []
        held = 0
        out = np.empty(t, np.float64)
        for k, s in enumerate(range(0, t, self.batch)):
            e = min(t, s + self.batch)
            if k < len(cached):
                fg = cached[k]
                fp = None if same else self.features(pred[s:e])
            else:
                # each side in a run of its own, so a frame's features (to the last bit) do not depend on
                # whether the ground truth's came from the cache or were computed beside the prediction's
                fg = self.features(gt[s:e])
                fp = None if same else self.features(pred[s:e])
            out[s:e] = 0.0 if same else self.distance(fp, fg)
            if building and len(keep) == k:  # a prefix of the clip, as much as the budget holds
                size = sum(f.nbytes for f in fg)
                if held + size <= self.cache_bytes:
                    keep.append(fg)
                    held += size
        if building:
            self._gt_key, self._gt_feats = gt_key, keep
            kept = min(t, len(keep) * self.batch)
            self.cache_note = "" if kept == t else (
                f"ground-truth features cached for {kept} of {t} frames (the rest are recomputed for every clip "
                f"scored against them): the budget is {self.cache_bytes / 2**30:.1f} GiB (LMGS_GT_CACHE_GB)")
        return out

    def update(self, pred: np.ndarray, gt: np.ndarray, gt_key: str | None = None, same: bool = False) -> dict[str, np.ndarray]:
        return {"per_item": self.distances(pred, gt, gt_key, same)}

    def stream(self, gt_key: str | None = None, same: bool = False):
        """The metric suite's feed (:meth:`~lmgs_eval.metrics.base.FloatFrames.stream`): uint8 chunks, converted a
        batch at a time here; with ``gt_key`` (one call on whole clips) the ground truth's features are kept."""
        return lambda pred, gt: self.update(pred, gt, gt_key, same)

    def compute(self, stats: dict[str, np.ndarray]) -> MetricResult:
        r = mean_result(self.spec, stats["per_item"], [])
        if self.spec.standin:
            r.notes.append("standin: " + self.spec.standin)
        r.notes.append("frames scored as float32 [0,1] (not re-encoded)")
        if self.cache_note:  # the last call's ground truth did not fit the cache budget
            r.notes.append(self.cache_note)
        return r
