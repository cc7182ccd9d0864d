"""A tiny synthetic talking clip made with the rasterizer from a known Gaussian scene.

The "mouth" Gaussians of the ground-truth scene open and close with the loudness of the
audio, so a model that uses audio can fit the clip and one that ignores it cannot fully.
"""

from __future__ import annotations

import numpy as np
import torch

from lmgs.render import rasterize
from lmgs.types import Camera, TrainingClip


def synthetic_clip(n: int = 24, size: int = 48, seed: int = 0) -> TrainingClip:
    g = torch.Generator().manual_seed(seed)
    nf = 300
    # A face: a disc of Gaussians at z = 0, facing the camera at z = +1 (OpenGL: looks down -z).
    r = torch.rand(nf, generator=g).sqrt() * 0.25
    th = torch.rand(nf, generator=g) * 2 * np.pi
    face = torch.stack([r * th.cos(), r * th.sin() * 1.2, torch.zeros(nf)], 1)
    face_col = torch.stack([0.8 - r, 0.6 - r, 0.5 - 0.5 * r], 1).clamp(0, 1)
    nm = 40
    mouth0 = torch.stack([(torch.rand(nm, generator=g) - 0.5) * 0.12, -0.12 + torch.zeros(nm), torch.full((nm,), 0.01)], 1)
    focal = size * 1.5
    t = np.arange(n * 640) / 16000.0
    env = 0.5 + 0.5 * np.sin(2 * np.pi * 1.5 * t)
    audio = (0.3 * env * np.sin(2 * np.pi * 300 * t)).astype(np.float32)
    open_amt = env[::640][:n]
    frames = np.empty((n, size, size, 3), np.uint8)
    depth = np.zeros((n, size, size), np.float16)
    normal = np.zeros((n, size, size, 3), np.int8)
    w2c = np.tile(np.eye(4, dtype=np.float32), (n, 1, 1))
    lms3d = np.zeros((n, 68, 3), np.float32)
    base_lms = np.concatenate([np.random.default_rng(seed).uniform(-0.2, 0.2, (60, 2)), np.zeros((8, 2))], 0)
    for i in range(n):
        yaw = 0.05 * np.sin(i / 5)
        c2w = np.eye(4)
        c2w[:3, :3] = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        c2w[:3, 3] = [np.sin(yaw), 0, np.cos(yaw)]
        w2c[i] = np.linalg.inv(c2w @ np.diag([1.0, -1, -1, 1]))
        cam = Camera(torch.from_numpy(w2c[i]), focal, focal, size / 2, size / 2, size, size)
        mouth = mouth0.clone()
        mouth[:, 1] -= 0.06 * float(open_amt[i]) * (torch.arange(nm) % 2)
        means = torch.cat([face, mouth])
        cols = torch.cat([face_col, torch.tensor([[0.3, 0.05, 0.05]]).repeat(nm, 1)])
        quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(len(means), 1)
        ls = torch.log(torch.tensor([[0.03, 0.03, 0.003]])).repeat(len(means), 1)
        ls[nf:] = np.log(0.02)
        op = torch.full((len(means),), 3.0)
        res = rasterize(means, quats, ls, op, cols, cam, torch.tensor([0.1, 0.2, 0.3]))
        frames[i] = (res.rgb.clamp(0, 1) * 255 + 0.5).byte().numpy()
        a = res.alpha[..., 0].numpy()
        depth[i] = np.where(a > 0.5, res.depth[..., 0].numpy() / np.maximum(a, 1e-6), 0)
        nn_ = res.normal.numpy() / np.maximum(a[..., None], 1e-6)
        normal[i] = np.where(a[..., None] > 0.5, np.clip(np.rint(nn_ * 127), -127, 127), 0).astype(np.int8)
        lm = np.concatenate([base_lms, np.zeros((68, 1))], 1)
        lm[60:68] = [[-0.06 + 0.02 * k, -0.12 - 0.03 * float(open_amt[i]) * (k % 2), 0.0] for k in range(8)]
        lms3d[i] = lm
    bg = np.broadcast_to(np.array([0.1, 0.2, 0.3]) * 255, (1, size, size, 3)).round().astype(np.uint8)
    head = depth > 0
    return TrainingClip(frames=frames, backgrounds=bg.copy(), w2c=w2c, focal=focal, cx=size / 2, cy=size / 2, audio=audio,
                        blink=np.zeros(n, np.float32), landmarks3d=lms3d, head_masks=head, depth=depth, normal=normal)
