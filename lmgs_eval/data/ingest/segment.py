"""The person in a frame: MediaPipe's selfie segmentation model, run in the LiteRT interpreter.

The model (``models/selfie_segmentation.tflite``, Apache-2.0, shipped with the package and its
sha256 checked on load; ``models/README.md`` says where it comes from) sees the whole frame at
256x256 (RGB in [0, 1]) and gives each of its pixels the probability of being person (hair,
neck and shoulders included).

How a frame is fed (:meth:`PersonSegmenter.probability`): the ingest's frames are square crops
around the face, with the body cut off by the frame's sides and bottom. Fed as they are, the model
loses person where it meets those edges (a shoulder's last strip, a cap's top). With the frame
continued by a tenth of its side to the left, right and bottom (its edge pixels repeated) the
model keeps the person up to those edges. Measured against the bundled
generator's truth (``design.md``, "The person mask"): person IoU 0.963 -> 0.983 (astronaut), 0.928
-> 0.949 (hopper). The probability map comes back at the frame's size, upsampled bilinearly.

One :class:`PersonSegmenter` per process (:func:`segmenter`): the interpreter runs on one
thread, so each worker process of the ingest holds its own and the output of a frame does not
depend on how the frames were spread over processes.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from lmgs_eval.data.ingest import vendored
from lmgs_eval.errors import UserError

MODEL = vendored.FOLDER / "selfie_segmentation.tflite"  # shipped (:mod:`vendored`, ``models/README.md``)
WHAT, MODEL_SHA256 = vendored.MODELS[MODEL.name]  # the one list of shipped models and their sha256
SIDE = 256  # the model's input and output side
PAD = 0.1  # the frame is continued by this fraction of its side to the left, right and bottom


def check_model(path: Path = MODEL, sha256: str = MODEL_SHA256) -> Path:
    """``path`` when it holds the model; a missing or altered file is a :class:`UserError` naming it."""
    return vendored.checked(path, sha256, WHAT)


class PersonSegmenter:
    """Person probability per pixel of a frame: ``probability(img)``, float32 ``[H, W]`` in [0, 1]."""

    def __init__(self, path: Path = MODEL, sha256: str = MODEL_SHA256) -> None:
        from ai_edge_litert.interpreter import Interpreter

        path = check_model(path, sha256)
        self.interpreter = Interpreter(model_path=str(path), num_threads=1)
        vendored.allocate_quietly(self.interpreter)
        inp, out = self.interpreter.get_input_details()[0], self.interpreter.get_output_details()[0]
        if tuple(inp["shape"]) != (1, SIDE, SIDE, 3) or tuple(out["shape"]) != (1, SIDE, SIDE, 1):
            raise UserError(f"{path}: the person segmentation model takes {tuple(inp['shape'])} and gives "
                            f"{tuple(out['shape'])}, not (1, {SIDE}, {SIDE}, 3) and (1, {SIDE}, {SIDE}, 1)")
        self._in, self._out = inp["index"], out["index"]

    def run(self, rgb: np.ndarray) -> np.ndarray:
        """The model on one ``SIDE x SIDE`` RGB uint8 image: its probability map, float32 ``[SIDE, SIDE]``."""
        self.interpreter.set_tensor(self._in, (rgb.astype(np.float32) / np.float32(255.0))[None])
        self.interpreter.invoke()
        return np.clip(self.interpreter.get_tensor(self._out)[0, :, :, 0], 0.0, 1.0)

    def probability(self, img: np.ndarray) -> np.ndarray:
        """The person probability of each pixel of ``img`` (RGB uint8 ``[H, W, 3]``), float32 ``[H, W]``:
        the frame continued by :data:`PAD` of its side left, right and below (edge pixels repeated),
        scaled to the model's input, and the model's map scaled back (bilinear) and cut to the frame."""
        import cv2

        h, w = img.shape[:2]
        pad = int(round(PAD * max(h, w)))
        big = cv2.copyMakeBorder(np.ascontiguousarray(img), 0, pad, pad, pad, cv2.BORDER_REPLICATE)
        bh, bw = big.shape[:2]
        shrink = cv2.INTER_AREA if max(bh, bw) > SIDE else cv2.INTER_LINEAR
        p = self.run(cv2.resize(big, (SIDE, SIDE), interpolation=shrink))
        return cv2.resize(p, (bw, bh), interpolation=cv2.INTER_LINEAR)[:h, pad:pad + w]


@functools.lru_cache(maxsize=1)
def segmenter() -> PersonSegmenter:
    """This process's :class:`PersonSegmenter` of the shipped model (loaded and checked once)."""
    return PersonSegmenter()
