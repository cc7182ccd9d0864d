"""A generic audio-to-lip model: the 20 mouth landmarks of any speaker from speech, retargeted to a subject.

:class:`LipModel` is a small temporal convolutional network: per 25 fps frame, the log-mel window of
:mod:`lmgs.audio` (``[16, 80]``, standardised per recording by :func:`feature_stats`) is summarised by
1D convolutions over its spectrogram steps; dilated convolutions over the frame sequence (17 frames
seen, 680 ms) give the mouth's 20 points (landmarks 48-67 of the iBUG 68) as **deltas from the
speaker's neutral mouth**, in a pose- and identity-normalised frame:

.. math::

    \\delta_t = \\big(A(M_t) - \\tilde M\\big) / w, \\qquad \\tilde M = \\operatorname{median}_t A(M_t),
    \\quad w = \\lVert \\tilde M_{48} - \\tilde M_{54} \\rVert

with :math:`A` the similarity that maps the face's skull-fixed landmarks (nose bridge and base, eye
corners: :data:`STABLE`) onto a canonical face (MediaPipe's canonical face model at the 68 points,
metres, OpenCV axes; the model carries it as ``template``), :math:`\\tilde M` the recording's median
(neutral) mouth and :math:`w` its width. One set of weights serves every speaker; a subject's
mouth is :math:`A^{-1}(\\tilde M + w\\, \\hat\\delta_t)` with the subject's own neutral mouth, width and
frame (:class:`RetargetedLips`).

The shipped weights (``lips_models/``, :data:`lmgs.lips_weights.WEIGHTS`, their sha256 checked on load) are made by
``scripts/train_lip_model.py``: pretrained on clips of the bundled generator (its synthetic voices
reading its corpus, the mouth the generator animates as the target), then adapted on lip tracks of
real speakers (about 100 s of eleven people's development footage, tracked with the dense face
mesh). They are a model of those recordings, not the recordings.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from lmgs.errors import InputError
from lmgs.lips_weights import DEFAULT, WEIGHTS, weights_file, weights_sha256

MOUTH = slice(48, 68)  # the mouth's 20 points of the 68
N_MOUTH = 20
# Skull-fixed points of the 68 the pose is fitted on: nose bridge and base (27-35), outer and inner
# eye corners (36, 39, 42, 45); lids and brows move, the jaw and lips speak.
STABLE = (27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 39, 42, 45)
GAP = (14, 18)  # inner-lip midpoints (62, 66) among the 20 mouth points
CORNERS = (0, 6)  # outer lip corners (48, 54)
IN_CHANNELS, WINDOW = 80, 16  # lmgs's default log-mel front end (AudioConfig())
CLIP_Z = 6.0  # standardised features are clipped to +-this

GAIN_MIN, GAIN_MAX = 0.05, 2.0  # the calibrated gain's range (see RetargetedLips.fit)
TUNE_STEPS = 400  # fine-tuning steps on a subject's own training split (train.landmark_source = generic-tuned)


# ----------------------------------------------------------------------------- normalisation
def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s R src + t`` of ``[P, 3]`` point sets (Umeyama): ``(s, R, t)``, ``R`` proper."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2] = -1.0
    rot = u @ np.diag(d) @ vt
    s = float((sig * d).sum() / max((a**2).sum() / len(src), 1e-18))
    return s, rot, mu_d - s * rot @ mu_s


@dataclass(frozen=True)
class Frame:
    """A similarity ``x -> s R x + t`` into the canonical frame, and back."""

    s: float
    R: np.ndarray
    t: np.ndarray

    def to_canonical(self, x: np.ndarray) -> np.ndarray:
        return self.s * np.asarray(x, np.float64) @ self.R.T + self.t

    def from_canonical(self, y: np.ndarray) -> np.ndarray:
        return ((np.asarray(y, np.float64) - self.t) @ self.R) / self.s


def canonical_frame(lms68: np.ndarray, template: np.ndarray) -> Frame:
    """The similarity taking the median of 68-point sets ``[T, 68, 3]`` (or one ``[68, 3]``) onto ``template``
    on the :data:`STABLE` points (a subject whose head is fixed in its world, as in the ER-NeRF layout)."""
    x = np.asarray(lms68, np.float64)
    if x.ndim == 3:
        x = np.median(x, axis=0)
    if x.shape != (68, 3):
        raise InputError(f"landmarks must be [T, 68, 3] or [68, 3], got shape {np.asarray(lms68).shape}")
    st = list(STABLE)
    return Frame(*similarity(x[st], np.asarray(template, np.float64)[st]))


def neutral_mouth(mouth: np.ndarray) -> tuple[np.ndarray, float]:
    """A recording's neutral mouth ``[20, 3]`` (the per-point median over frames ``[T, 20, 3]``) and its width
    (outer corner to corner)."""
    m = np.asarray(mouth, np.float64)
    if m.ndim != 3 or m.shape[1:] != (N_MOUTH, 3) or len(m) == 0:
        raise InputError(f"mouth points must be [T>0, 20, 3], got shape {m.shape}")
    n = np.median(m, axis=0)
    w = float(np.linalg.norm(n[CORNERS[0]] - n[CORNERS[1]]))
    if not w > 0:
        raise InputError("the neutral mouth has no width (corner points coincide)")
    return n, w


def lip_gap(points) -> np.ndarray:
    """Inner-lip gap per frame ``[T]``: the distance between the inner-lip midpoints (62, 66), read from the
    mouth's 20 points ``[T, 20, D]`` or from all 68 ``[T, 68, D]`` (D = 2 or 3; a missing face's NaN stays NaN)."""
    m = np.asarray(points, np.float64)
    if m.ndim == 3 and m.shape[1] == 68:
        m = m[:, MOUTH]
    if m.ndim != 3 or m.shape[1] != N_MOUTH:
        raise InputError(f"lip_gap reads [T, 20, D] mouth points or [T, 68, D] landmarks, got shape {m.shape}")
    return np.linalg.norm(m[:, GAP[0]] - m[:, GAP[1]], axis=-1)


def feature_stats(feats) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and standard deviation ``([C], [C])`` of a recording's feature windows ``[N, W, C]``."""
    f = np.asarray(feats, np.float64)
    if f.ndim != 3 or len(f) == 0:
        raise InputError(f"features must be [N>0, W, C], got shape {f.shape}")
    flat = f.reshape(-1, f.shape[2])
    return flat.mean(0).astype(np.float32), np.maximum(flat.std(0), 1e-3).astype(np.float32)


def logmel(audio, n_frames: int) -> np.ndarray:
    """The model's input: lmgs's default log-mel windows ``[n_frames, 16, 80]`` of a 16 kHz waveform, whatever
    front end the rest of a model reads."""
    from lmgs.audio import compute_features

    return compute_features(audio, 16000, None, n_frames=n_frames)


def standardise(feats, stats: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Features standardised by a recording's :func:`feature_stats`, clipped to +-:data:`CLIP_Z`."""
    mu, sd = stats
    return np.clip((np.asarray(feats, np.float32) - mu) / sd, -CLIP_Z, CLIP_Z).astype(np.float32)


# ----------------------------------------------------------------------------- the network
class LipModel(nn.Module):
    """Standardised log-mel windows ``[N, 16, 80]`` of consecutive frames -> mouth deltas ``[N, 20, 3]``
    (units of the neutral mouth's width, canonical axes). ``template`` ``[68, 3]``: the canonical face
    the pose is normalised to."""

    def __init__(self, in_channels: int = IN_CHANNELS, window: int = WINDOW, hidden: int = 96):
        super().__init__()
        self.in_channels, self.window, self.hidden = int(in_channels), int(window), int(hidden)
        act = lambda: nn.LeakyReLU(0.02)  # noqa: E731
        self.frame = nn.Sequential(
            nn.Conv1d(in_channels, 64, 3, padding=1), act(),
            nn.Conv1d(64, 64, 3, stride=2, padding=1), act(),
            nn.Conv1d(64, 64, 3, stride=2, padding=1), act(),
        )
        self.proj = nn.Linear(64 * ((window + 3) // 4), hidden)
        self.temporal = nn.ModuleList([
            nn.Conv1d(hidden, hidden, 5, padding=2),
            nn.Conv1d(hidden, hidden, 3, padding=2, dilation=2),
            nn.Conv1d(hidden, hidden, 3, padding=4, dilation=4),
        ])
        self.act = act()
        self.head = nn.Conv1d(hidden, 3 * N_MOUTH, 1)
        self.register_buffer("template", torch.zeros(68, 3))

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        """``[N, W, C]`` (one sequence) or ``[B, N, W, C]`` -> ``[N, 20, 3]`` / ``[B, N, 20, 3]``."""
        one = feats.ndim == 3
        x = feats[None] if one else feats
        if x.ndim != 4 or x.shape[2:] != (self.window, self.in_channels):
            raise InputError(f"lip model expects [N, {self.window}, {self.in_channels}] features, got {tuple(feats.shape)}")
        B, N = x.shape[:2]
        h = self.frame(x.reshape(B * N, self.window, self.in_channels).transpose(1, 2))
        h = self.act(self.proj(h.flatten(1))).view(B, N, -1).transpose(1, 2)  # [B, H, N]
        for conv in self.temporal:
            h = h + self.act(conv(h))
        out = self.head(h).transpose(1, 2).reshape(B, N, N_MOUTH, 3)
        return out[0] if one else out

    @torch.no_grad()
    def predict(self, feats_std) -> np.ndarray:
        """Deltas ``[N, 20, 3]`` for standardised features ``[N, W, C]`` of one contiguous sequence."""
        f = torch.as_tensor(np.asarray(feats_std, np.float32))
        if f.shape[0] == 0:
            return np.zeros((0, N_MOUTH, 3), np.float32)
        was = self.training
        self.eval()
        out = self(f).numpy()
        self.train(was)
        return out


def n_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


# ----------------------------------------------------------------------------- training
@dataclass
class LipSequence:
    """One recording for training: standardised features ``[N, W, C]`` and target deltas ``[N, 20, 3]``."""

    feats: np.ndarray
    deltas: np.ndarray


def train_lip_model(
    model: LipModel,
    data: Sequence[LipSequence],
    *,
    steps: int,
    seed: int = 0,
    lr: float = 2e-3,
    batch: int = 16,
    length: int = 64,
    extra: Sequence[LipSequence] = (),
    extra_share: float = 0.0,
    spec_mask: int = 8,
    progress: Callable[[int, float], None] | None = None,
) -> LipModel:
    """Adam on random ``length``-frame windows of ``data`` (whole sequences where shorter), mean squared delta
    error; a share ``extra_share`` of each batch is drawn from ``extra`` (e.g. generated clips kept while adapting
    on real ones). Each window loses one random band of up to ``spec_mask`` mel channels (regularisation).
    Deterministic for a seed and a thread count (the global RNGs are left untouched). Returns ``model``, trained."""
    if not data:
        raise InputError("no sequences to train the lip model on")
    rng = np.random.default_rng(seed)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=max(steps, 1), pct_start=0.1)
    pools = [(list(data), 1.0 - (extra_share if extra else 0.0))] + ([(list(extra), extra_share)] if extra else [])
    weights = [np.array([len(s.feats) for s in p], np.float64) for p, _ in pools]
    model.train()
    for step in range(steps):
        xs, ys = [], []
        for b in range(batch):
            k = 0 if len(pools) == 1 or rng.random() >= pools[1][1] else 1
            seqs = pools[k][0]
            s = seqs[rng.choice(len(seqs), p=weights[k] / weights[k].sum())]
            n = len(s.feats)
            L = min(length, n)
            a = int(rng.integers(0, n - L + 1))
            x = s.feats[a:a + L].copy()
            if spec_mask:
                w = int(rng.integers(0, spec_mask + 1))
                c0 = int(rng.integers(0, x.shape[2] - w + 1))
                x[:, :, c0:c0 + w] = 0.0
            xs.append(x)
            ys.append(s.deltas[a:a + L])
        L = min(len(x) for x in xs)  # windows from sequences shorter than `length` set the batch's length
        x = torch.from_numpy(np.stack([v[:L] for v in xs]))
        y = torch.from_numpy(np.stack([v[:L] for v in ys]).astype(np.float32))
        loss = ((model(x) - y) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if progress is not None and (step % 100 == 0 or step == steps - 1):
            progress(step, float(loss.detach()))
    model.eval()
    return model


def new_model(template: np.ndarray, seed: int = 0) -> LipModel:
    """A freshly initialised :class:`LipModel` (seeded, global RNG untouched) carrying ``template`` ``[68, 3]``."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        m = LipModel()
    m.template.copy_(torch.as_tensor(np.asarray(template, np.float32)))
    return m


# ----------------------------------------------------------------------------- files
def save(model: LipModel, path: str | Path) -> None:
    """The weights as a torch file whose bytes depend on the weights only (same weights: same sha256)."""
    import io

    from lmgs.fileio import atomic_write

    buf = io.BytesIO()
    state = {k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}
    torch.save({"args": {"in_channels": model.in_channels, "window": model.window, "hidden": model.hidden},
                "state": state}, buf)
    atomic_write(path, buf.getvalue())


def load(name_or_path: str | Path = DEFAULT, *, check: bool = True) -> LipModel:
    """A shipped model (a key of :data:`lmgs.lips_weights.WEIGHTS`, its sha256 checked) or a weights file."""
    p = weights_file(name_or_path, check=check)
    blob = torch.load(p, map_location="cpu", weights_only=True)
    m = LipModel(**blob["args"])
    m.load_state_dict(blob["state"])
    m.eval()
    return m


# ----------------------------------------------------------------------------- a subject's mouth
class RetargetedLips:
    """The generic lip model fitted to one subject: its frame, neutral mouth, width and audio statistics.

    ``predict(feats [N, 16, 80] raw log-mel) -> [N, 20, 3]`` mouth points in the subject's world.
    """

    def __init__(self, model: LipModel, frame: Frame, neutral: np.ndarray, width: float,
                 stats: tuple[np.ndarray, np.ndarray], name: str = DEFAULT, tuned_frames: int = 0,
                 offset: np.ndarray | None = None, gain: np.ndarray | None = None, sha256: str | None = None):
        self.model, self.frame, self.neutral, self.width = model, frame, np.asarray(neutral, np.float64), float(width)
        self.stats, self.name, self.tuned_frames = stats, str(name), int(tuned_frames)
        # the weights' sha256 (shipped or a file; given when the caller has it already); "" for a model handed over in
        # memory under a label
        if sha256 is None:
            sha256 = weights_sha256(name) if str(name) in WEIGHTS or Path(name).is_file() else ""
        self.sha256 = sha256
        self.offset = np.zeros((N_MOUTH, 3)) if offset is None else np.asarray(offset, np.float64)
        self.gain = np.ones(3) if gain is None else np.asarray(gain, np.float64)

    @classmethod
    def fit(cls, feats, landmarks3d, *, model: LipModel | None = None, name: str = DEFAULT,
            tune_steps: int = 0, seed: int = 0) -> "RetargetedLips":
        """Retarget to a subject from its training features ``[N, W, C]`` and 68 landmarks ``[N, 68, 3]``
        (world, head fixed): neutral mouth and width from the landmarks' median, audio statistics from the
        features; the predicted neutral and per-axis gain calibrated on them (below); with ``tune_steps``
        the model is fine-tuned on the subject's own deltas instead."""
        f = np.asarray(feats, np.float32)
        y = np.asarray(landmarks3d, np.float64)
        if y.ndim != 3 or y.shape[1:] != (68, 3) or len(y) != len(f):
            raise InputError(f"landmarks3d must be [N={len(f)}, 68, 3], got shape {y.shape}")
        model = load(name) if model is None else model
        fr = canonical_frame(y, model.template.numpy())
        mouth = fr.to_canonical(y[:, MOUTH])
        neutral, width = neutral_mouth(mouth)
        stats = feature_stats(f)
        target = ((mouth - neutral) / width).astype(np.float32)
        if tune_steps > 0:
            import copy

            model = copy.deepcopy(model)
            train_lip_model(model, [LipSequence(standardise(f, stats), target)], steps=tune_steps, seed=seed, lr=1e-3,
                            batch=8, spec_mask=0)
            return cls(model, fr, neutral, width, stats, name, len(f))
        # Calibration on the subject's training split, where the untuned model's predictions are out of sample:
        # the predicted neutral moved onto the subject's, and per axis the least-squares gain (in [GAIN_MIN,
        # GAIN_MAX]) of the predicted motion: a speaker whose motion the model foresees poorly is damped towards
        # the neutral mouth instead of being given motion of the wrong size.
        pred = model.predict(standardise(f, stats)).astype(np.float64)
        offset = np.median(pred, axis=0)
        a, b = (pred - offset).reshape(-1, 3), target.reshape(-1, 3).astype(np.float64)
        gain = np.clip((a * b).sum(0) / np.maximum((a * a).sum(0), 1e-12), GAIN_MIN, GAIN_MAX)
        return cls(model, fr, neutral, width, stats, name, 0, offset, gain)

    def to_state(self) -> dict:
        """What a checkpoint keeps: the retargeting, and the weights themselves only when fine-tuned (else the
        shipped file's name and sha256, read again on load)."""
        return {"name": self.name, "sha256": self.sha256, "s": self.frame.s,
                "R": self.frame.R.tolist(), "t": self.frame.t.tolist(), "neutral": self.neutral.tolist(),
                "width": self.width, "stats": [self.stats[0].tolist(), self.stats[1].tolist()],
                "tuned_frames": self.tuned_frames, "offset": self.offset.tolist(), "gain": self.gain.tolist(),
                "state": ({k: v.clone() for k, v in self.model.state_dict().items()} if self.tuned_frames else None),
                "args": {"in_channels": self.model.in_channels, "window": self.model.window, "hidden": self.model.hidden}}

    @classmethod
    def from_state(cls, st: dict) -> "RetargetedLips":
        have = None
        if st.get("state") is not None:
            model = LipModel(**st["args"])
            model.load_state_dict(st["state"])
            model.eval()
        else:
            have = weights_sha256(st["name"])
            if st.get("sha256") and have != st["sha256"]:
                raise InputError(f"the checkpoint's lip model {st['name']} (sha256 {str(st['sha256'])[:12]}...) is not "
                                 f"the one {'installed' if st['name'] in WEIGHTS else 'there now'} (sha256 {have[:12]}...)")
            model = load(st["name"])
        frame = Frame(float(st["s"]), np.asarray(st["R"], np.float64), np.asarray(st["t"], np.float64))
        stats = (np.asarray(st["stats"][0], np.float32), np.asarray(st["stats"][1], np.float32))
        return cls(model, frame, np.asarray(st["neutral"]), float(st["width"]), stats, st["name"], st.get("tuned_frames", 0),
                   np.asarray(st["offset"]), np.asarray(st["gain"]), sha256=have)

    def deltas(self, feats) -> np.ndarray:
        """Calibrated deltas ``[N, 20, 3]`` (units of the neutral width, canonical axes)."""
        return (self.model.predict(standardise(feats, self.stats)) - self.offset) * self.gain

    def canonical(self, feats) -> np.ndarray:
        """Mouth points ``[N, 20, 3]`` in the canonical frame (the subject's neutral plus its scaled deltas)."""
        return self.neutral + self.width * self.deltas(feats)

    def predict(self, feats) -> np.ndarray:
        """Mouth points ``[N, 20, 3]`` in the subject's world."""
        return self.frame.from_canonical(self.canonical(feats)).astype(np.float32)

    def with_mouth(self, lms68: torch.Tensor, feats) -> torch.Tensor:
        """``lms68`` ``[N, 68, 3]`` (a copy) with its mouth (48-67) predicted from raw log-mel windows ``[N, 16, 80]``."""
        out = lms68.clone()
        out[:, MOUTH] = torch.from_numpy(self.predict(feats)[: len(out)]).to(out)
        return out

    def replace_mouth(self, lms68: torch.Tensor, audio, n_frames: int) -> torch.Tensor:
        """``lms68`` ``[N, 68, 3]`` (a copy) with its mouth (48-67) predicted from the waveform ``audio``."""
        return self.with_mouth(lms68, logmel(audio, n_frames))

    def describe(self) -> dict:
        return {
            "name": "lmgs.lips.LipModel",
            "weights": self.name,
            "weights_sha256": self.sha256,
            "role": "audio-to-lip model for the mouth landmarks (48-67) guiding Spatial Enhancement and Landmark Compensation",
            "note": (f"generic model ({WEIGHTS[self.name][0] if self.name in WEIGHTS else 'weights from ' + self.name}), "
                     "retargeted to this subject's neutral mouth, width and pose frame, its predicted neutral and "
                     "per-axis amplitude calibrated on the training split"
                     + (f"; fine-tuned on {self.tuned_frames} training frames" if self.tuned_frames else "")),
            "neutral_width": round(self.width, 6),
            "gain_xyz": [round(float(g), 3) for g in self.gain],
        }


def retarget_for(source: str, audio, n_frames: int, landmarks3d, seed: int = 0,
                 weights: str | Path = DEFAULT) -> RetargetedLips | None:
    """The generic model retargeted to a subject for a landmark source (``train.landmark_source``): ``None`` for
    ``subject``, fitted on the training audio (a 16 kHz waveform of ``n_frames`` frames) and 68 landmarks
    ``[n_frames, 68, 3]`` for ``generic``, and fine-tuned on them too for ``generic-tuned``. ``weights``: a
    shipped model's name or a weights file (``train.lip_weights``)."""
    if source == "subject":
        return None
    return RetargetedLips.fit(logmel(audio, n_frames), np.asarray(landmarks3d, np.float32), name=str(weights),
                              tune_steps=TUNE_STEPS if source == "generic-tuned" else 0, seed=seed)
