"""The one ``Subject`` type every part of the toolkit reads.

A subject is a talking-head video processed into the ER-NeRF / TalkingGaussian layout
(the repository's ``docs/field.md``). Frames are read lazily from disk; everything small
(cameras, landmarks, audio, blink track) is held in memory.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lmgs.types import Camera
from lmgs_eval.data.audio import SAMPLE_RATE
from lmgs_eval.data.bundled_spec import knee_density
from lmgs_eval.data.images import read_depth, read_normal, read_rgb, read_rgb_u8, read_rgba

FPS = 25


@dataclass(frozen=True)
class Subject:
    """A processed talking-head subject.

    Attributes:
        name: subject name (folder name).
        root: the subject folder.
        width, height: frame size in pixels.
        focal, cx, cy: pinhole intrinsics in pixels (``focal_len``, ``cx``, ``cy`` of transforms).
        c2w: ``[N, 4, 4]`` camera-to-world per frame, OpenGL convention, as in
            ``transforms_*.json`` (see :meth:`lmgs.types.Camera.from_nerf_c2w`).
        landmarks: ``[N, 68, 2]`` 2D landmarks in pixels (from ``ori_imgs/<i>.lms``).
        audio: ``[S]`` float32 mono waveform in [-1, 1] at 16 kHz.
        blink: ``[N]`` AU45_r (eye blink intensity, 0-5), zeros when ``au.csv`` is absent.
        aus: every ``AUxx_r`` column of ``au.csv`` by name (``"AU45_r"``), ``[N]`` each.
        train_ids, test_ids: frame indices of the split (first ``int(N*10/11)`` train).
        landmarks3d: ``[N, 68, 3]`` world-space landmarks when the subject has them.
        audio_features: precomputed features by kind: ``"ds"`` ``[N, 16, 29]``,
            ``"hu"`` ``[N, 2, 1024]``, ``"eo"``, ``"wavlm"``..., each aligned to frames.
        bundled: True for a subject made by the project's generator (a stand-in, never
            the paper's data); ``meta`` then says how it was made.
        notes: repairs applied while reading (resampling, mixing to mono...), one per line.
        meta: free-form metadata (``meta.json`` of bundled subjects).
        head_prior: where the folder has no depth/normal maps, a head ellipsoid derived from its
            landmarks and cameras (:mod:`lmgs_eval.data.complete`); :meth:`depth` and
            :meth:`normal` then ray-cast it inside the head parsing mask. ``notes`` say so.
    """

    name: str
    root: Path
    width: int
    height: int
    focal: float
    cx: float
    cy: float
    c2w: np.ndarray
    landmarks: np.ndarray
    audio: np.ndarray
    blink: np.ndarray
    aus: dict[str, np.ndarray]
    train_ids: np.ndarray
    test_ids: np.ndarray
    landmarks3d: np.ndarray | None = None
    audio_features: dict[str, np.ndarray] = field(default_factory=dict)
    bundled: bool = False
    notes: tuple[str, ...] = ()
    meta: dict = field(default_factory=dict)
    fps: int = FPS
    sample_rate: int = SAMPLE_RATE
    head_prior: object | None = None  # lmgs_eval.data.complete.HeadPrior

    # ------------------------------------------------------------------ sizes
    @property
    def budget_density(self) -> float | None:
        """Gaussians per face pixel at this subject's capacity knee, when it is not the preset's.

        Set for the bundled subjects whose measured knee is not at the quick preset's density
        (:data:`lmgs_eval.data.bundled_spec.KNEE_DENSITY`); None otherwise. Methods that size their
        Gaussians by face area take it (:func:`baselines.protocol.create_method`).
        """
        return knee_density(self.meta) if self.bundled else None

    @property
    def n_frames(self) -> int:
        return int(self.c2w.shape[0])

    @property
    def duration(self) -> float:
        return self.n_frames / self.fps

    def samples_per_frame(self) -> int:
        return self.sample_rate // self.fps

    def audio_for(self, ids: np.ndarray) -> np.ndarray:
        """The waveform covering the contiguous frame range ``ids`` (e.g. the test split)."""
        ids = np.asarray(ids)
        spf = self.samples_per_frame()
        return self.audio[int(ids[0]) * spf : (int(ids[-1]) + 1) * spf]

    # ------------------------------------------------------------------ images
    def _img(self, folder: str, i: int, ext: str) -> Path:
        return self.root / folder / f"{int(i)}.{ext}"

    def frame(self, i: int) -> np.ndarray:
        """Ground-truth frame ``i`` (``gt_imgs``) as uint8 ``[H, W, 3]`` RGB."""
        return read_rgb_u8(self._img("gt_imgs", i, "jpg"))

    def frames(self, ids) -> np.ndarray:
        """Frames ``ids`` stacked: uint8 ``[T, H, W, 3]`` RGB."""
        return np.stack([self.frame(i) for i in ids]) if len(ids) else np.zeros((0, self.height, self.width, 3), np.uint8)

    def original_frame(self, i: int) -> np.ndarray:
        """Frame ``i`` as recorded (``ori_imgs``), uint8 ``[H, W, 3]`` RGB."""
        return read_rgb_u8(self._img("ori_imgs", i, "jpg"))

    def background(self) -> np.ndarray:
        """``bc.jpg`` as float32 ``[H, W, 3]`` in [0, 1]."""
        return read_rgb(self.root / "bc.jpg")

    def torso(self, i: int) -> np.ndarray | None:
        """``torso_imgs/<i>.png`` as float32 RGBA ``[H, W, 4]`` in [0, 1], or None if absent."""
        p = self._img("torso_imgs", i, "png")
        return read_rgba(p) if p.exists() else None

    def parsing(self, i: int) -> np.ndarray | None:
        """``parsing/<i>.png`` as uint8 RGB ``[H, W, 3]`` (ER-NeRF colours), or None."""
        p = self._img("parsing", i, "png")
        return read_rgb_u8(p) if p.exists() else None

    def mouth_mask(self, i: int) -> np.ndarray | None:
        """``teeth_mask/<i>.npy`` (inside-mouth mask) as bool ``[H, W]``, or None."""
        p = self._img("teeth_mask", i, "npy")
        return np.load(p).astype(bool) if p.exists() else None

    def depth(self, i: int) -> np.ndarray | None:
        """Depth map ``[H, W]`` float32 (camera z, world units; 0 = background), or None."""
        p = self._img("depth", i, "png")
        if p.exists():
            return read_depth(p, float(self.meta.get("depth_scale", 1000.0)))
        return self._prior(i)[0] if self.head_prior is not None else None

    def _prior(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Depth and normals of the derived head prior in frame ``i`` (inside the head mask)."""
        p = self.parsing(i)
        mask = np.all(p == (255, 0, 0), axis=-1) if p is not None else np.ones((self.height, self.width), bool)
        w2c = self.camera(i).world_to_camera.numpy().astype(np.float64)
        return self.head_prior.render(w2c, self.focal, self.cx, self.cy, self.width, self.height, mask)

    def normal(self, i: int) -> np.ndarray | None:
        """Normal map ``[H, W, 3]`` float32, unit camera-space normals (OpenCV axes), or None."""
        p = self._img("normal", i, "png")
        if p.exists():
            return read_normal(p)
        return self._prior(i)[1] if self.head_prior is not None else None

    @property
    def has_geometry(self) -> bool:
        return ((self.root / "depth").is_dir() and (self.root / "normal").is_dir()) or self.head_prior is not None

    @property
    def priors_derived(self) -> bool:
        """Whether the depth / normal priors are derived from the tracking rather than measured: the
        head ellipsoid ray-cast at load (:attr:`head_prior`) or an ingest's ellipsoid / face-mesh maps
        (``meta.json`` says ``ingested``). A bundled subject's maps are its rendered head and a folder's own
        maps from elsewhere count as measured; ``meta.json``'s ``priors_derived``, where given, decides
        (a copy of an ingest holding the generator's maps says False). False without priors."""
        if not self.has_geometry:
            return False
        return self.head_prior is not None or bool(self.meta.get("priors_derived", self.meta.get("ingested", False)))

    def camera(self, i: int):
        """The :class:`lmgs.types.Camera` of frame ``i``."""
        return Camera.from_nerf_c2w(self.c2w[i], self.focal, self.width, self.height, self.cx, self.cy)

    def describe(self) -> dict:
        """A small JSON-able summary (for ``lmgs-eval subjects --json`` and results files)."""
        return {
            "name": self.name,
            "path": str(self.root),
            "frames": self.n_frames,
            "width": self.width,
            "height": self.height,
            "fps": self.fps,
            "seconds": round(self.duration, 3),
            "train_frames": int(len(self.train_ids)),
            "test_frames": int(len(self.test_ids)),
            "audio_features": sorted(self.audio_features),
            "landmarks3d": self.landmarks3d is not None,
            "geometry": self.has_geometry,
            "geometry_derived": self.priors_derived,
            "bundled": self.bundled,
            "standin": self.meta.get("standin") if self.bundled else None,
            "budget_density": self.budget_density,
            "notes": list(self.notes),
        }
