"""Blink from the face mesh: MediaPipe's face blendshape model run on the tracked 478 points.

MediaPipe's Face Landmarker turns 146 of its 478 landmarks into 52 ARKit-style blendshape scores
in [0, 1] with a small model (``models/face_blendshapes.tflite``, Apache-2.0, shipped with the
package and its sha256 checked on load; ``models/README.md`` says where it comes from). The model
reads only where the points are, not the image: :func:`blendshapes` feeds it the points of
:meth:`lmgs_eval.data.ingest.mesh.FaceMesh.track`, and :func:`au45` makes the two eyelid scores a
stand-in for OpenFace's blink intensity ``AU45_r``.

What the model is fed, as MediaPipe's ``FaceBlendshapesGraph`` feeds it: the x and y of the
:data:`SUBSET` points, in that order, in the frame's pixels (MediaPipe's landmarks are normalized to
the frame and multiplied back by its width and height), one face a call, ``[1, 146, 2]`` float32;
z is not read. The model measures the points against themselves: moving all of them or scaling
them by one factor leaves its scores unchanged (to 1e-5), stretching one axis does not, which is why
x and y must share one unit. Points in pixels, as the mesh gives them, meet that for any frame
size, so the frame's size is not an argument here. Fed the Face Landmarker's own landmarks (MediaPipe
1.2.3, a real clip and the bundled subjects, 2,500 frames), :func:`blendshapes` gives its 52 scores to
5e-6; on the mesh of :mod:`~lmgs_eval.data.ingest.mesh` the blink of a real clip follows the Face
Landmarker's at r = 0.95.
"""

from __future__ import annotations

import functools
import threading
from pathlib import Path

import numpy as np

from lmgs_eval.errors import UserError

MODEL = "face_blendshapes.tflite"  # in the shipped models (:mod:`vendored`)

# The mesh vertices the model reads, in the order it reads them (MediaPipe's
# face_blendshapes_graph.cc, kLandmarksSubsetIdxs): brows, eyelids, nose, lips, jaw outline, and the
# ten iris points 468-477.
SUBSET = np.array([
    0, 1, 4, 5, 6, 7, 8, 10, 13, 14, 17, 21, 33, 37, 39, 40,
    46, 52, 53, 54, 55, 58, 61, 63, 65, 66, 67, 70, 78, 80, 81, 82,
    84, 87, 88, 91, 93, 95, 103, 105, 107, 109, 127, 132, 133, 136, 144, 145,
    146, 148, 149, 150, 152, 153, 154, 155, 157, 158, 159, 160, 161, 162, 163, 168,
    172, 173, 176, 178, 181, 185, 191, 195, 197, 234, 246, 249, 251, 263, 267, 269,
    270, 276, 282, 283, 284, 285, 288, 291, 293, 295, 296, 297, 300, 308, 310, 311,
    312, 314, 317, 318, 321, 323, 324, 332, 334, 336, 338, 356, 361, 362, 365, 373,
    374, 375, 377, 378, 379, 380, 381, 382, 384, 385, 386, 387, 388, 389, 390, 397,
    398, 400, 402, 405, 409, 415, 454, 466, 468, 469, 470, 471, 472, 473, 474, 475,
    476, 477,
])

# The model's 52 scores, in its output order (MediaPipe's kBlendshapeNames; ARKit's names).
NAMES = (
    "_neutral",
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight",
    "eyeBlinkLeft", "eyeBlinkRight",
    "eyeLookDownLeft", "eyeLookDownRight", "eyeLookInLeft", "eyeLookInRight",
    "eyeLookOutLeft", "eyeLookOutRight", "eyeLookUpLeft", "eyeLookUpRight",
    "eyeSquintLeft", "eyeSquintRight", "eyeWideLeft", "eyeWideRight",
    "jawForward", "jawLeft", "jawOpen", "jawRight",
    "mouthClose", "mouthDimpleLeft", "mouthDimpleRight", "mouthFrownLeft", "mouthFrownRight",
    "mouthFunnel", "mouthLeft", "mouthLowerDownLeft", "mouthLowerDownRight",
    "mouthPressLeft", "mouthPressRight", "mouthPucker", "mouthRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthSmileLeft", "mouthSmileRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthUpperUpLeft", "mouthUpperUpRight", "noseSneerLeft", "noseSneerRight",
)
EYE_BLINK_LEFT, EYE_BLINK_RIGHT = NAMES.index("eyeBlinkLeft"), NAMES.index("eyeBlinkRight")  # 9, 10
AU45_MAX = 5.0  # the top of OpenFace's intensity scale


class Blendshapes:
    """The blendshape model in a LiteRT interpreter: :meth:`__call__` scores one face's 146 points."""

    def __init__(self, path: Path | None = None):
        from ai_edge_litert.interpreter import Interpreter

        from lmgs_eval.data.ingest import vendored

        path = vendored.model(MODEL, path)
        self.interpreter = Interpreter(model_path=str(path), num_threads=1)  # a small model: more threads gain nothing
        vendored.allocate_quietly(self.interpreter)
        (inp,), (out,) = self.interpreter.get_input_details(), self.interpreter.get_output_details()
        if tuple(inp["shape"]) != (1, len(SUBSET), 2) or tuple(out["shape"]) != (len(NAMES),):
            raise UserError(f"{path}: the face blendshape model takes {tuple(inp['shape'])} and gives "
                            f"{tuple(out['shape'])}, not (1, 146, 2) and (52,)")
        self._in, self._out = inp["index"], out["index"]
        self._lock = threading.Lock()  # one interpreter holds one input and one output buffer

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """The 52 scores ``[52]`` of one face from its :data:`SUBSET` points ``[146, 2]`` in pixels."""
        x = np.ascontiguousarray(xy, np.float32).reshape(1, len(SUBSET), 2)
        with self._lock:
            self.interpreter.set_tensor(self._in, x)
            self.interpreter.invoke()
            return self.interpreter.get_tensor(self._out).astype(np.float32)


@functools.lru_cache(maxsize=1)
def shared() -> Blendshapes:
    """The shipped model, loaded (and its file checked) once per process."""
    return Blendshapes()


def blendshapes(points: np.ndarray, model: Blendshapes | None = None) -> np.ndarray:
    """The 52 blendshape scores ``[T, 52]`` (in :data:`NAMES` order, each in [0, 1]) of a tracked mesh.

    ``points``: ``[T, 478, 2+]`` in image pixels, as :meth:`~lmgs_eval.data.ingest.mesh.FaceMesh.track`
    gives them (only x and y are read). A frame whose model points are not all finite (no face
    found) gives a row of NaN.

    The sides are the subject's, as in ARKit: ``eyeBlinkLeft`` is the subject's left eye, on the
    right of an unmirrored frame (mesh vertex 263's side).
    """
    pts = np.asarray(points, np.float32)
    if pts.ndim != 3 or pts.shape[1] != 478 or pts.shape[2] < 2:
        raise ValueError(f"points of shape {pts.shape}: expected [T, 478, 2 or 3]")
    model = model if model is not None else shared()
    xy = pts[:, SUBSET, :2]
    out = np.full((len(pts), len(NAMES)), np.nan, np.float32)
    for t in np.flatnonzero(np.isfinite(xy).all(axis=(1, 2))):
        out[t] = model(xy[t])
    return out


def au45(points: np.ndarray, model: Blendshapes | None = None) -> np.ndarray:
    """A stand-in for OpenFace's ``AU45_r`` (blink, 0-5) per frame ``[T]``: ``5 x`` the mean of
    ``eyeBlinkLeft`` and ``eyeBlinkRight``, NaN where the mesh is.

    How and why: the two blink scores are the model's eyelid closure of each eye, 0 open to 1
    closed; OpenFace's intensity scale runs from 0 (absent) to 5 (maximal), and the bundled subjects
    write ``AU45_r = 5 x eyelid closure``, so the same factor puts the two on one scale; OpenFace has
    one AU45 for both eyes, hence the mean. The map is fixed, not fitted to the clip (the eye aspect
    ratio's stand-in, :func:`lmgs_eval.data.ingest.writer.action_units`, takes the clip's usual
    openness as zero), so a clip without a blink stays low. The model's scores seldom reach the
    ends: measured, open eyes give 0.2-0.8 (up to 1 when lowered or narrowed), the blinks of two
    real speakers 2.1-2.5, a mesh whose lids are put together 3.9.
    Its open-eye level drifts (with gaze, pitch, expression); taking that level out (a running
    median) follows the generator's blinks more closely (r 0.88 against 0.77 on the astronaut's
    60 s at 256 px), but lmgs trained on it rendered a real clip's eyes slightly worse on both
    seeds tried, as the drift is the eyes' state too (``design.md``, "Blinks from the blendshape
    model"): the score is written as it is.

    Against the bundled subjects' true blink (512 px, 60 s, hair moving with the head) the Pearson
    r is 0.65 (astronaut) and 0.63 (hopper), the eye aspect ratio of dlib's points 0.87 and 0.24
    (20 s at 256 px: 0.80 and 0.62 against 0.75 and 0.33). The generator's drawn lids are a weak
    picture of a closed eye, which the mesh's lids follow only part of the way (and hopper's eyes
    are behind glasses); MediaPipe's own Face Landmarker scores no better on the same frames (0.75
    and 0.56 over 20 s at 512 px, where this gives 0.71 and 0.62).

    This is computed from the mesh's geometry, not OpenFace's appearance-based ``AU45_r``.
    """
    s = blendshapes(points, model)
    return np.clip(AU45_MAX * 0.5 * (s[:, EYE_BLINK_LEFT] + s[:, EYE_BLINK_RIGHT]), 0.0, AU45_MAX)
