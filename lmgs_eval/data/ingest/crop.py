"""The square window cut out of each frame: placed on the head, the same for the whole clip.

The window is fixed over the clip on purpose. The layout's methods render the head in front of
one static plate (``bc.jpg``): a window that moved with the head would move the background
inside the frame and break that assumption, and would turn head motion into camera motion the
pose fit could not tell apart. So the window is centred on the head's median position, made
large enough that the face stays inside it over the whole clip, and shifted (never shrunk) to
stay inside the frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Window side over the jaw width (landmarks 0-16): the face fills about 40 % of the width, as
# in the field's processed subjects (Obama, May) and the bundled ones (35-42 %).
JAW_FRACTION = 0.40
ALREADY_CROPPED = 0.85  # a near-square video whose window would cover this much is used whole


@dataclass(frozen=True)
class Window:
    """A square window ``[x0, x0 + side) x [y0, y0 + side)`` in source pixels, output ``size``."""

    x0: float
    y0: float
    side: float
    size: int
    whole: bool  # the whole (square) frame is used: the video is already a head crop

    @property
    def scale(self) -> float:
        return self.size / self.side

    def to_out(self, pts: np.ndarray) -> np.ndarray:
        """Source pixel coordinates (continuous) to output pixel coordinates."""
        return (np.asarray(pts, np.float64) - [self.x0, self.y0]) * self.scale

    def matrix(self) -> np.ndarray:
        """The 2x3 affine for ``cv2.warpAffine`` in pixel-index convention."""
        s = self.scale
        return np.array([[s, 0, 0.5 * s - 0.5 - s * self.x0], [0, s, 0.5 * s - 0.5 - s * self.y0]], np.float64)

    def apply(self, img: np.ndarray) -> np.ndarray:
        import cv2

        interp = cv2.INTER_AREA if self.scale < 1 else cv2.INTER_CUBIC
        if self.whole and self.x0 == 0 and self.y0 == 0 and img.shape[0] == img.shape[1] == self.size:
            return img
        if self.scale < 1:  # area filter: crop first, then resize
            x0, y0, s = int(round(self.x0)), int(round(self.y0)), int(round(self.side))
            return cv2.resize(img[y0 : y0 + s, x0 : x0 + s], (self.size, self.size), interpolation=interp)
        return cv2.warpAffine(img, self.matrix(), (self.size, self.size), flags=interp, borderMode=cv2.BORDER_REPLICATE)

    def to_json(self) -> dict:
        return {"x0": self.x0, "y0": self.y0, "side": self.side, "size": self.size, "whole_frame": self.whole}


def choose_window(lms: np.ndarray, width: int, height: int, size: int, mode: str = "auto") -> tuple[Window, list[str]]:
    """The clip's window from its landmarks ``[N, 68, 2]`` (source pixels).

    ``mode``: ``"auto"`` (crop unless the video already is a head crop), ``"head"`` (always
    crop around the head), ``"none"`` (use the whole frame, centre-cropped to a square).
    """
    notes: list[str] = []
    short = min(width, height)
    jaw = np.linalg.norm(lms[:, 16] - lms[:, 0], axis=1)
    side = float(np.median(jaw)) / JAW_FRACTION
    centre = np.stack([0.5 * (lms[:, 0, 0] + lms[:, 16, 0]), lms[:, 30, 1]], 1)
    c = np.median(centre, axis=0)
    # keep every frame's face (its landmark box plus a margin) inside the window
    reach = np.max(np.abs(lms - c[None, None]), axis=(0, 1)) * 1.15
    side = max(side, 2 * float(reach.max()))
    square = abs(width - height) <= 0.02 * max(width, height)
    whole = mode == "none" or (mode == "auto" and square and side >= ALREADY_CROPPED * short)
    if whole or side >= short:
        if not whole:
            notes.append(f"the head needs a {side:.0f} px window but the frame is {width}x{height}; using the largest square")
        side = float(short)
        x0, y0 = (width - side) / 2, (height - side) / 2
        if not square:
            x0 = float(np.clip(c[0] - side / 2, 0, width - side))
            y0 = float(np.clip(c[1] - side / 2, 0, height - side))
        return Window(round(x0), round(y0), side, size, whole), notes
    x0 = float(np.clip(c[0] - side / 2, 0, width - side))
    y0 = float(np.clip(c[1] - side / 2, 0, height - side))
    return Window(round(x0), round(y0), round(side), size, False), notes
