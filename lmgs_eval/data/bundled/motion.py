"""Optional motion of a bundled clip beyond the speech motion: a turning head, a zooming camera.

The default clips hold what a processed talking-head video of the field holds: a near-frontal
head (yaw within a few degrees) before a fixed camera. Two variants test what an ingest does
outside that:

* ``turn``: the head sweeps its yaw ``yaw_deg * sin(2 pi t / T)`` and its pitch
  ``pitch_deg * sin(4 pi t / T)`` (a figure of eight: large yaw with and without pitch) on top
  of the speech motion; ``T`` is the clip's length unless ``period_s`` is given, so every clip
  starts frontal and turns both ways once.
* ``zoom``: the camera's focal length is ``focal * (1 + zoom * sin(2 pi t / T))`` (the head
  and the camera stay where they were). A zoom scales the whole image about the principal point,
  so the torso and the background scale with the head; where zooming out uncovers the border of
  the photo, the border is mirrored.

``t`` is the frame centre ``(i + 0.5) / fps`` as in :func:`articulation.articulation`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from lmgs_eval.data.bundled import exact
from lmgs_eval.errors import UserError

KINDS = ("turn", "zoom")


@dataclass(frozen=True)
class Motion:
    """Extra motion of a clip (see the module docstring).

    Attributes:
        kind: ``turn`` or ``zoom``.
        yaw_deg, pitch_deg: amplitudes of the turn (degrees).
        zoom: relative amplitude of the focal length's change.
        period_s: seconds of one cycle; None: the clip's length.
    """

    kind: str
    yaw_deg: float = 28.0
    pitch_deg: float = 10.0
    zoom: float = 0.08
    period_s: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise UserError(f"motion {self.kind!r}: unknown (known: {', '.join(KINDS)})")
        if not (0 <= self.yaw_deg <= 60 and 0 <= self.pitch_deg <= 30):
            raise UserError(f"motion turn of {self.yaw_deg:g} deg yaw, {self.pitch_deg:g} deg pitch: at most 60 and 30")
        if not (0 <= self.zoom <= 0.3):
            raise UserError(f"motion zoom {self.zoom:g}: must be between 0 and 0.3 (relative focal change)")
        if self.period_s is not None and not self.period_s > 0:
            raise UserError(f"motion period {self.period_s}: must be positive")

    @staticmethod
    def of(motion: "Motion | str | None") -> "Motion | None":
        """``None``, a kind's name (its default amplitudes) or a :class:`Motion`."""
        if motion is None or isinstance(motion, Motion):
            return motion
        return Motion(str(motion))

    def _phase(self, n: int, fps: int) -> np.ndarray:
        t = (np.arange(n) + 0.5) / fps
        period = self.period_s if self.period_s is not None else n / fps
        return 2 * np.pi * t / period

    def apply(self, art: np.ndarray, fps: int) -> np.ndarray:
        """The articulation ``[N, K]`` with the turn added to its yaw and pitch (a copy)."""
        from lmgs_eval.data.bundled.articulation import COLUMNS

        out = np.array(art, copy=True)
        if self.kind == "turn":
            ph = self._phase(len(art), fps)
            out[:, COLUMNS.index("yaw")] += (self.yaw_deg * exact.sin(ph)).astype(out.dtype)
            out[:, COLUMNS.index("pitch")] += (self.pitch_deg * exact.sin(2 * ph)).astype(out.dtype)
        return out

    def focals(self, n: int, fps: int, focal: float) -> np.ndarray | None:
        """Focal length per frame ``[N]`` (pixels) for a zoom; None when the focal is fixed."""
        if self.kind != "zoom":
            return None
        return float(focal) * (1.0 + self.zoom * exact.sin(self._phase(n, fps)))

    def to_json(self) -> dict:
        return asdict(self)
