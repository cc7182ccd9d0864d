"""PLY export/import in the standard 3DGS layout (Inria ``save_ply`` / ``load_ply``).

One binary little-endian ``vertex`` element with float32 properties, in this order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1}
    opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

``opacity`` is the logit, ``scale_*`` the log-scales, ``rot_*`` the quaternion (wxyz);
``nx ny nz`` are zeros. ``f_rest`` is stored channel-major, as 3DGS does
(``features_rest.transpose(1, 2).flatten(1)``: all R coefficients, then G, then B).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from lmgs.errors import InputError


@dataclass
class GaussianPly:
    """Gaussian parameters as stored in a 3DGS PLY (float32, CPU)."""

    means: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4] wxyz
    log_scales: torch.Tensor  # [N, 3]
    opacity_logits: torch.Tensor  # [N]
    sh: torch.Tensor  # [N, K, 3], K = (degree + 1)^2; sh[:, 0] is f_dc

    @property
    def sh_degree(self) -> int:
        return int(round(self.sh.shape[1] ** 0.5)) - 1


def save_ply(path: str | Path, g: GaussianPly) -> Path:
    """Write ``g`` to ``path`` (binary little-endian); returns the path."""
    n, k = g.sh.shape[0], g.sh.shape[1]
    cols: list[tuple[str, np.ndarray]] = []
    mean = g.means.detach().cpu().float().numpy()
    cols += [(a, mean[:, i]) for i, a in enumerate("xyz")]
    cols += [(a, np.zeros(n, np.float32)) for a in ("nx", "ny", "nz")]
    sh = g.sh.detach().cpu().float().numpy()
    cols += [(f"f_dc_{i}", sh[:, 0, i]) for i in range(3)]
    rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1))
    cols += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    cols += [("opacity", g.opacity_logits.detach().cpu().float().numpy().reshape(n))]
    ls = g.log_scales.detach().cpu().float().numpy()
    cols += [(f"scale_{i}", ls[:, i]) for i in range(3)]
    q = g.quats.detach().cpu().float().numpy()
    cols += [(f"rot_{i}", q[:, i]) for i in range(4)]
    arr = np.empty(n, dtype=[(name, "<f4") for name, _ in cols])
    for name, v in cols:
        arr[name] = v
    path = Path(path)
    PlyData([PlyElement.describe(arr, "vertex")], byte_order="<").write(str(path))
    return path


def load_ply(path: str | Path) -> GaussianPly:
    """Read a 3DGS PLY; raises :class:`InputError` naming a missing property."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"PLY file not found: {path}")
    ply = PlyData.read(str(path))
    if "vertex" not in ply:
        raise InputError(f"{path}: no 'vertex' element")
    v = ply["vertex"].data
    names = set(v.dtype.names or ())
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)]
    need += [f"rot_{i}" for i in range(4)]
    missing = [p for p in need if p not in names]
    if missing:
        raise InputError(f"{path}: missing 3DGS properties {missing}")
    n_rest = len([p for p in names if re.fullmatch(r"f_rest_\d+", p)])
    k = 1 + n_rest // 3
    if n_rest % 3 or int(round(k**0.5)) ** 2 != k:
        raise InputError(f"{path}: {n_rest} f_rest properties is not 3 * ((d+1)^2 - 1)")

    def stack(props: list[str]) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(v[p], np.float32) for p in props], axis=1))

    n = len(v)
    sh = torch.zeros(n, k, 3)
    sh[:, 0] = stack([f"f_dc_{i}" for i in range(3)])
    if n_rest:
        sh[:, 1:] = stack([f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k - 1).transpose(1, 2)
    return GaussianPly(
        means=stack(["x", "y", "z"]),
        quats=stack([f"rot_{i}" for i in range(4)]),
        log_scales=stack([f"scale_{i}" for i in range(3)]),
        opacity_logits=stack(["opacity"])[:, 0],
        sh=sh,
    )
