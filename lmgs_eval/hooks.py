"""What the toolkit lends the method adapters: the ``hooks`` of :func:`baselines.protocol.create_method`.

The adapters import nothing of :mod:`lmgs_eval`; where one needs what only the toolkit has, it
names a hook and takes it as a keyword argument (see :mod:`baselines.protocol`). The protocols
(:func:`lmgs_eval.runner.build_method`) and ``lmgs-eval methods`` pass :func:`adapter_hooks`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def adapter_hooks() -> dict:
    """``read_frames`` (:func:`read_frames`, for ``external:NAME``) and ``sync_loss`` for Wav2Lip's expert
    lip-sync loss, ``sync_loss(lower_faces [B, 3, h, w] in [0, 1], audio_windows [B, 16, 80]) -> scalar``.

    ``sync_loss`` is None: none of the toolkit's sync scorers is a differentiable image model at
    Wav2Lip's crop size (the landmark scorer reads landmarks, the pixel scorer 224 px crops), so
    Wav2Lip trains without the expert loss and its description says so. Code that has such a loss
    passes it to :func:`baselines.protocol.create_method` itself."""
    return {"read_frames": read_frames, "sync_loss": None}


def read_frames(path: Path) -> np.ndarray:
    """A video or a folder of images as uint8 ``[T, H, W, 3]``, a frame decoded at a time (a gap in a
    folder's numbering is a :class:`~lmgs_eval.errors.UserError`)."""
    from lmgs_eval.data.frames import FrameFile

    return FrameFile(path).read()
