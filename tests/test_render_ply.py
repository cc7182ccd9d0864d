"""3DGS PLY round trip."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData

from lmgs.errors import InputError
from lmgs.render.ply import GaussianPly, load_ply, save_ply


@pytest.mark.parametrize("k", [1, 4, 16])
def test_round_trip(tmp_path, k):
    g = torch.Generator().manual_seed(k)
    n = 25
    src = GaussianPly(
        torch.randn(n, 3, generator=g),
        torch.randn(n, 4, generator=g),
        torch.randn(n, 3, generator=g),
        torch.randn(n, generator=g),
        torch.randn(n, k, 3, generator=g),
    )
    path = save_ply(tmp_path / "g.ply", src)
    back = load_ply(path)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert torch.equal(getattr(back, name), getattr(src, name)), name
    assert back.sh_degree == int(round(k**0.5)) - 1
    # the standard attribute order and channel-major f_rest of Inria's save_ply
    props = [p.name for p in PlyData.read(str(path))["vertex"].properties]
    n_rest = 3 * (k - 1)
    assert props == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [
        f"f_rest_{i}" for i in range(n_rest)
    ] + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    if k > 1:
        v = PlyData.read(str(path))["vertex"].data
        # f_rest_1 is the second coefficient of the red channel
        assert np.float32(v["f_rest_1"][0]) == src.sh[0, 2, 0].item()


def test_missing_property(tmp_path):
    from plyfile import PlyElement

    arr = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "bad.ply"))
    with pytest.raises(InputError, match="missing 3DGS properties"):
        load_ply(tmp_path / "bad.ply")
