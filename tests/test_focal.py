"""The focal length from the dense mesh (:mod:`lmgs_eval.data.ingest.focal`), against synthetic
views of a face whose camera is known."""

from __future__ import annotations


import numpy as np
import pytest

from lmgs_eval.data.ingest import focal as focal_mod
from lmgs_eval.errors import UserError

W = 512


def _views(f_widths: float, distance: float, yaw_deg: float, seed: int = 0, noise_px: float = 0.3) -> np.ndarray:
    """A face (the canonical one with every point moved by a few millimetres: not the prior's shape)
    seen by a camera of focal ``f_widths`` frame widths at ``distance`` metres, turning up to
    ``yaw_deg`` either way and nodding a third of that; mesh points ``[N, 468, 3]`` in pixels."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    face = focal_mod.canonical_face()
    face = face + rng.normal(0, 0.003, face.shape)
    f = f_widths * W
    t = np.linspace(0, 2 * np.pi, 40)
    rots = Rotation.from_euler("yx", np.stack([yaw_deg * np.sin(t), yaw_deg / 3 * np.sin(2 * t)], 1), degrees=True)
    pc = np.einsum("nij,pj->npi", rots.as_matrix(), face) + [0.0, 0.0, distance]
    uv = f * pc[..., :2] / pc[..., 2:3] + W / 2 + rng.normal(0, noise_px, pc[..., :2].shape)
    return np.concatenate([uv, np.zeros_like(uv[..., :1])], -1)


def test_a_near_turning_head_decides_the_focal_length():
    """A head filling a third of the frame, 40 cm away, turning +-35 deg: the perspective is strong and
    the clip's own evidence decides; the estimate is near the truth (1.4 widths: far from the prior's
    2.5) and its interval holds it."""
    truth = 1.4
    fit = focal_mod.fit_focal(_views(truth, 0.4, 35.0), W, W)
    assert fit.evidence > 1.0
    assert abs(fit.focal / W / truth - 1) < 0.2, fit.focal / W
    assert fit.lo <= truth * W <= fit.hi


def test_a_still_distant_head_leaves_the_focal_length_to_the_prior():
    """A head 1.5 m away that hardly turns (+-3 deg): the clip says little, the record says so (evidence
    below 1), and the interval is wide around the prior and holds the truth (3 widths)."""
    fit = focal_mod.fit_focal(_views(3.0, 1.5, 3.0), W, W)
    assert fit.lo <= 3.0 * W <= fit.hi
    assert fit.evidence < 1.0
    assert fit.hi / fit.lo > 2.0
    assert fit.lo < focal_mod.PRIOR_WIDTHS * W < fit.hi
    assert fit.to_json(W)["evidence"] == round(fit.evidence, 3)


def test_frames_without_a_face_are_left_out_and_too_few_is_an_error():
    mesh = _views(2.0, 0.6, 20.0)
    mesh[::2] = np.nan
    assert focal_mod.fit_focal(mesh, W, W, frames=10).frames == 10
    mesh[2:] = np.nan
    with pytest.raises(UserError, match="too few"):
        focal_mod.fit_focal(mesh, W, W)
