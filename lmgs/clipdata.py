"""A training clip's per-frame arrays as the training step reads them, without a host sync on a GPU.

Copying a host array to a CUDA tensor (``tensor.to("cuda")`` from ordinary, pageable memory)
makes the host wait until the GPU has run everything queued before the copy. A training step that
uploads its frame, background, mouth mask, depth and normal maps, audio index and blink value
would stall the GPU and the Python thread in turn half a dozen times a step, and a small model's
step on a GPU is bound by exactly that kind of wait (its kernels take a fraction of the step).

:class:`ClipTensors` uploads each array once, in its stored dtype (uint8 frames, float16 depth,
int8 normals), when the whole clip fits in a quarter of the device's free memory, and converts a
step's frame there. On the CPU, and on a GPU too small for the clip, it reads each frame from the
arrays per step as before. Both give the same values, bit for bit.

The mouth mask is kept as the flat indices of its pixels (row-major, the order in which a boolean
mask selects them), computed on the host: selecting with them gives the same elements in the same
order as the mask, and a step never asks the device how many pixels a mask holds.
"""

from __future__ import annotations

import numpy as np
import torch

from lmgs.types import TrainingClip

# share of the device's free memory the uploaded clip may take
DEVICE_SHARE = 0.25


def _nbytes(clip: TrainingClip) -> int:
    arrays = (clip.frames, clip.backgrounds, clip.mouth_masks, clip.depth, clip.normal, clip.blink)
    return sum(int(a.nbytes) for a in arrays if a is not None)


def fits_on_device(clip: TrainingClip, dev: torch.device) -> bool:
    """True when ``dev`` is a GPU whose free memory holds :data:`DEVICE_SHARE` of it for the clip."""
    if dev.type != "cuda":
        return False
    free, _ = torch.cuda.mem_get_info(dev)
    return _nbytes(clip) <= DEVICE_SHARE * free


def as_image(x: torch.Tensor) -> torch.Tensor:
    """uint8 ``[..., 3]`` -> float in [0, 1], on its device."""
    return x.float() / 255.0


def to_image(x: np.ndarray, device) -> torch.Tensor:
    """uint8 ``[H, W, 3]`` -> float ``[H, W, 3]`` in [0, 1] on ``device``."""
    return as_image(torch.from_numpy(np.ascontiguousarray(x)).to(device))


class ClipTensors:
    """Per-frame tensors of ``clip`` on ``dev`` (see the module docstring).

    ``frame(i)``, ``background(i)`` are float ``[H, W, 3]`` in [0, 1]; ``depth(i)`` float32 ``[H, W]``;
    ``normal(i)`` float32 ``[H, W, 3]`` (the stored int8 over 127); ``blink(i)`` a 0-d float32 tensor;
    ``index(i)`` the int64 ``[1]`` frame index (on the host); ``mouth_pixels(i)`` the flat indices of the mouth
    mask's pixels, or None when the frame has none (or the clip no masks).
    """

    def __init__(self, clip: TrainingClip, dev: torch.device):
        self.clip, self.dev = clip, dev
        self.resident = fits_on_device(clip, dev)
        up = (lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(dev)) if self.resident else None
        self._frames = up(clip.frames) if up else None
        self._backgrounds = up(clip.backgrounds) if up else None
        self._depth = up(clip.depth) if up and clip.depth is not None else None
        self._normal = up(clip.normal) if up and clip.normal is not None else None
        self._blink = torch.from_numpy(np.ascontiguousarray(clip.blink, np.float32)).to(dev)
        self._index = torch.arange(len(clip))  # on the host: AudioNet works out the window's frames there
        self._mouth = None
        if clip.mouth_masks is not None:
            flat = [np.flatnonzero(m) for m in clip.mouth_masks]
            ends = np.cumsum([0] + [len(f) for f in flat])
            self._mouth = (torch.from_numpy(np.concatenate(flat).astype(np.int64)).to(dev), ends)

    def frame(self, i: int) -> torch.Tensor:
        return as_image(self._frames[i]) if self.resident else to_image(self.clip.frames[i], self.dev)

    def background(self, i: int) -> torch.Tensor:
        k = i if self.clip.backgrounds.shape[0] > 1 else 0
        return as_image(self._backgrounds[k]) if self.resident else to_image(self.clip.backgrounds[k], self.dev)

    def depth(self, i: int) -> torch.Tensor:
        if self.resident:
            return self._depth[i].float()
        return torch.from_numpy(self.clip.depth[i].astype(np.float32)).to(self.dev)

    def normal(self, i: int) -> torch.Tensor:
        if self.resident:
            return self._normal[i].float() / 127.0
        return torch.from_numpy(self.clip.normal[i].astype(np.float32) / 127.0).to(self.dev)

    def blink(self, i: int) -> torch.Tensor:
        return self._blink[i]

    def index(self, i: int) -> torch.Tensor:
        return self._index[i : i + 1]

    def mouth_pixels(self, i: int) -> torch.Tensor | None:
        if self._mouth is None:
            return None
        flat, ends = self._mouth
        a, b = int(ends[i]), int(ends[i + 1])
        return flat[a:b] if b > a else None
