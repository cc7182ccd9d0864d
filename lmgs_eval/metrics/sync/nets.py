"""The SyncNet-style networks of LSE: syncnet_python's ``S`` (official weights, imported) and the bundled pixel scorer.

Torch is needed only here, to import the official weights (``lmgs-eval weights import-syncnet``) or to
export a trained bundled scorer; scoring runs the exported ONNX graphs (:mod:`~lmgs_eval.metrics.sync.scorers`).
"""

from __future__ import annotations

import json
from pathlib import Path

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.sync import scorers
from lmgs_eval.metrics.sync.crops import CROP_SIZE


def _build_nets():
    from torch import nn

    class SyncNetS(nn.Module):
        """syncnet_python's ``S`` (docs/field.md, "SyncNet S, the network LSE is defined with"), state-dict compatible.

        ``forward(audio [N,1,13,20], video [N,3,5,224,224]) -> (a_emb, v_emb)`` (1024-d each).
        """

        def __init__(self):
            super().__init__()
            bn2, bn3 = nn.BatchNorm2d, nn.BatchNorm3d
            self.netcnnaud = nn.Sequential(
                nn.Conv2d(1, 64, 3, 1, 1), bn2(64), nn.ReLU(), nn.MaxPool2d(1, 1),
                nn.Conv2d(64, 192, 3, 1, 1), bn2(192), nn.ReLU(), nn.MaxPool2d(3, (1, 2)),
                nn.Conv2d(192, 384, 3, padding=1), bn2(384), nn.ReLU(),
                nn.Conv2d(384, 256, 3, padding=1), bn2(256), nn.ReLU(),
                nn.Conv2d(256, 256, 3, padding=1), bn2(256), nn.ReLU(), nn.MaxPool2d(3, 2),
                nn.Conv2d(256, 512, (5, 4)), bn2(512), nn.ReLU(),
            )
            self.netfcaud = nn.Sequential(nn.Linear(512, 512), nn.BatchNorm1d(512), nn.ReLU(), nn.Linear(512, 1024))
            self.netfclip = nn.Sequential(nn.Linear(512, 512), nn.BatchNorm1d(512), nn.ReLU(), nn.Linear(512, 1024))
            self.netcnnlip = nn.Sequential(
                nn.Conv3d(3, 96, (5, 7, 7), (1, 2, 2), 0), bn3(96), nn.ReLU(), nn.MaxPool3d((1, 3, 3), (1, 2, 2)),
                nn.Conv3d(96, 256, (1, 5, 5), (1, 2, 2), (0, 1, 1)), bn3(256), nn.ReLU(),
                nn.MaxPool3d((1, 3, 3), (1, 2, 2), (0, 1, 1)),
                nn.Conv3d(256, 256, (1, 3, 3), padding=(0, 1, 1)), bn3(256), nn.ReLU(),
                nn.Conv3d(256, 256, (1, 3, 3), padding=(0, 1, 1)), bn3(256), nn.ReLU(),
                nn.Conv3d(256, 256, (1, 3, 3), padding=(0, 1, 1)), bn3(256), nn.ReLU(),
                nn.MaxPool3d((1, 3, 3), (1, 2, 2)),
                nn.Conv3d(256, 512, (1, 6, 6)), bn3(512), nn.ReLU(),
            )

        def forward(self, audio, video):
            a = self.netfcaud(self.netcnnaud(audio).flatten(1))
            v = self.netfclip(self.netcnnlip(video).flatten(1))
            return a, v

    class BundledSyncNet(nn.Module):
        """A small SyncNet-style scorer for the bundled subjects (same interface, fewer FLOPs).

        audio ``[N,1,13,20]``: 3 conv-BN-ReLU (32, 64, 128; strides 1, (1,2), 2), global mean, Linear 128.
        video ``[N,3,5,H,W]`` (lower half of the face crop, 0..1): Conv3d 3-32 k(5,5,5) s(1,2,2) p(0,2,2)
        collapsing time, then 3 conv-BN-ReLU (64, 128, 128; stride 2), global mean, Linear 128.
        The embeddings are compared by L2 distance exactly as SyncNet's.
        """

        def __init__(self, dim: int = 128):
            super().__init__()

            def cbr(i, o, s):
                return [nn.Conv2d(i, o, 3, s, 1), nn.BatchNorm2d(o), nn.ReLU()]

            self.aud = nn.Sequential(*cbr(1, 32, 1), *cbr(32, 64, (1, 2)), *cbr(64, 128, 2))
            self.aud_fc = nn.Linear(128, dim)
            self.lip3d = nn.Sequential(nn.Conv3d(3, 32, (5, 5, 5), (1, 2, 2), (0, 2, 2)), nn.BatchNorm3d(32), nn.ReLU())
            self.lip = nn.Sequential(*cbr(32, 64, 2), *cbr(64, 128, 2), *cbr(128, 128, 2))
            self.lip_fc = nn.Linear(128, dim)

        def forward(self, audio, video):
            a = self.aud_fc(self.aud(audio).mean(dim=(2, 3)))
            v = self.lip(self.lip3d(video)[:, :, 0])
            v = self.lip_fc(v.mean(dim=(2, 3)))
            return a, v

    return SyncNetS, BundledSyncNet


_NETS = None


def nets():
    """``(SyncNetS, BundledSyncNet)`` torch classes (built on first use)."""
    global _NETS
    if _NETS is None:
        _NETS = _build_nets()
    return _NETS


def _export_sync(net, path: Path, hw: tuple[int, int]) -> None:
    import torch

    from lmgs_eval.metrics.ort import export_onnx

    a = torch.randn(2, 1, 13, 20)
    v = torch.rand(2, 3, 5, *hw)
    export_onnx(net.eval(), (a, v), path, ["audio", "video"], ["a_emb", "v_emb"],
                {"audio": {0: "n"}, "video": {0: "n"}, "a_emb": {0: "n"}, "v_emb": {0: "n"}})


def import_syncnet(state_dict_path: Path) -> dict:
    """Convert the official ``syncnet_v2.model`` state dict to ONNX in the cache; return the manifest.

    Raises:
        UserError: unreadable file, keys/shapes not those of syncnet_python's ``S``, or a tensor holding NaN or Inf.
    """
    import torch

    from lmgs.fileio import sha256_file
    from lmgs_eval.metrics.ort import load_torch_state, onnx_cache_dir
    from lmgs.fileio import atomic_write

    src = Path(state_dict_path)
    sd = load_torch_state(src, "SyncNet state dict")
    S, _ = nets()
    net = S()
    own = net.state_dict()
    missing = [k for k in own if k not in sd]
    if missing:
        raise UserError(f"{src}: not syncnet_python's S layout, missing {len(missing)} key(s) e.g. {missing[0]!r}")
    for k, v in own.items():
        if tuple(sd[k].shape) != tuple(v.shape):
            raise UserError(f"{src}: key {k!r} has shape {tuple(sd[k].shape)}, expected {tuple(v.shape)}")
    for k in own:
        t = sd[k]
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            n_bad = int((~torch.isfinite(t)).sum())
            raise UserError(f"{src}: tensor {k!r} holds {n_bad} non-finite value(s) (NaN or Inf) of {t.numel()}; "
                            "these are not usable weights (a damaged or diverged checkpoint)")
    net.load_state_dict({k: sd[k] for k in own})
    sha = sha256_file(src)
    out = onnx_cache_dir() / f"{sha}-syncnet-v2.onnx"
    _export_sync(net, out, (CROP_SIZE, CROP_SIZE))
    manifest = {"name": "syncnet-v2", "source": str(src), "source_sha256": sha, "onnx": str(out),
                "onnx_sha256": sha256_file(out), "input_hw": [CROP_SIZE, CROP_SIZE], "region": "full",
                "pixel": "bgr_0_255"}
    atomic_write(scorers.syncnet_manifest_path(), json.dumps(manifest, indent=2))
    return manifest


def export_bundled(net, out_dir: Path, meta: dict) -> dict:
    """Write a trained :class:`BundledSyncNet` as ``bundled_sync.onnx`` + ``bundled_sync.json``.

    ``meta`` must hold the training ``recipe`` and ``seed``; the sha256 of the graph is
    added. For the engineer training the bundled scorer.
    """
    from lmgs.fileio import sha256_file
    from lmgs.fileio import atomic_write

    for k in ("recipe", "seed"):
        if k not in meta:
            raise UserError(f"bundled sync meta must include {k!r}")
    out_dir = Path(out_dir)
    hw = tuple(meta.get("input_hw", (48, 96)))
    _export_sync(net, out_dir / scorers.PIXEL_ONNX, hw)
    m = {"name": "bundled-sync", "input_hw": list(hw), "region": meta.get("region", "lower_half"),
         "pixel": meta.get("pixel", "bgr_0_1"), **meta, "sha256": sha256_file(out_dir / scorers.PIXEL_ONNX)}
    atomic_write(out_dir / scorers.PIXEL_JSON, json.dumps(m, indent=2))
    return m
