"""Training of the reference model: static stage, then dynamic stage (paper, "Training Detail").

* Static stage: the canonical face and mouth fields, L1 + D-SSIM on every training frame.
* Dynamic stage: the deformation networks, the audio net and the guidance modules switch on;
  the loss adds the Geometry Regularizer (when ``gr`` and the subject has depth/normal maps)
  and a term keeping the face transparent inside the mouth mask (TalkingGaussian's
  decomposition).

Densification and pruning run from :mod:`lmgs.strategy` under a Gaussian budget derived from
the face area. Checkpoints are written atomically every ``checkpoint_every`` steps and a run
resumes from the last one with the same config hash. A non-finite loss stops training with
a clear message and leaves the last good checkpoint in place, and so does a collapse: the
mean loss of the last ``COLLAPSE_WINDOW`` steps above ``COLLAPSE_FACTOR`` times the lowest
such mean seen earlier in the same stage (a 16,000-Gaussian hopper run once threw its face
off-screen this way: finite loss, 15 dB, no gradient to come back). The check only stops
runs; it never changes a run that passes it, so it is not part of the config hash.

:func:`fit` drives named stages over one run's state (:class:`_Run`): :func:`_start` (device,
seeds, audio features), :func:`_build_model` (budget, initial Gaussians), :func:`_fit_landmarks`
(the audio-to-landmark stand-in), :func:`_prepare` (optimisers, densification, resuming),
:func:`_step` for each step (:func:`_frame_loss`, :func:`_stop_if_failed`, the optimiser and
densification step of :mod:`lmgs.optim`, the curve and the checkpoint), :func:`_finish`. What
a run leaves on disk is :mod:`lmgs.checkpoint`'s.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from lmgs import losses
from lmgs.checkpoint import (
    psnr,
    resume,
    save_checkpoint,
    write_curve,
    write_failed_curve,
)
from lmgs.errors import InputError, TrainingDiverged  # noqa: F401 (TrainingDiverged re-exported)
from lmgs.gaussians import GaussianSet
from lmgs.clipdata import ClipTensors
from lmgs.init import face_area_px, init_face, init_mouth, scene_box
from lmgs.model import LMGSModel
from lmgs.optim import densify, gaussian_adam, network_adamw, optimise
from lmgs.strategy import Strategy, budget_from_face_area, initialize_state
from lmgs.types import TrainingClip

COLLAPSE_WINDOW = 25
COLLAPSE_FACTOR = 3.0


class CollapseGuard:
    """Rolling mean of the loss over ``window`` steps, against the lowest full-window mean of the stage.

    ``update(loss, stage)`` returns ``None``, or the ratio current/best when it exceeds ``factor``.
    """

    def __init__(self, window: int = COLLAPSE_WINDOW, factor: float = COLLAPSE_FACTOR):
        self.window, self.factor = int(window), float(factor)
        self.stage, self.buf, self.best = None, deque(maxlen=self.window), float("inf")

    def update(self, loss: float, stage: str) -> float | None:
        if stage != self.stage:  # each stage has its own loss terms and level
            self.stage, self.best = stage, float("inf")
            self.buf.clear()
        self.buf.append(float(loss))
        if len(self.buf) < self.window:
            return None
        mean = sum(self.buf) / self.window
        if self.best < float("inf") and mean > self.factor * self.best:
            return mean / self.best
        self.best = min(self.best, mean)
        return None


@dataclass
class FitReport:
    """What a training run produced and cost.

    ``seconds`` is the whole training's time: after a resume, the earlier runs' seconds up to
    their last checkpoint (``prior_seconds``, saved in it) plus this run's.
    """

    steps: int
    seconds: float
    n_gaussians: int
    budget: int
    final_psnr: float
    se_fraction: float
    resumed_from: int = 0
    landmark_seconds: float = 0.0
    curve: list = field(default_factory=list)
    prior_seconds: float = 0.0


@dataclass
class _Run:
    """The state one training run's stages share (see the module docstring)."""

    clip: TrainingClip
    cfg: object
    dev: torch.device
    say: Callable[[str], None]
    workdir: Path | None
    t_start: float
    feats: torch.Tensor
    model: LMGSModel | None = None
    budget: int = 0
    n_mouth: int = 0
    extent: float = 0.0
    lms_pred: torch.Tensor | None = None
    t_lms: float = 0.0
    g_opt: torch.optim.Optimizer | None = None
    n_opt: torch.optim.Optimizer | None = None
    strategies: tuple = ()
    states: tuple = ()
    ckpt: Path | None = None
    curve_rows: list = field(default_factory=list)
    start: int = 0
    prior: float = 0.0
    saved_at: int = 0
    bar: object = None
    guard: CollapseGuard = field(default_factory=CollapseGuard)
    last_psnr: float = float("nan")
    last_frac: float = float("nan")
    lip_boxes: np.ndarray | None = None
    mouth_states: torch.Tensor | None = None  # [T, 2] the training frames' normalised mouth state (guidance.mouth_state)
    use_geo: bool = False
    prior_weights: tuple[float, float] = (0.0, 0.0)  # the Geometry Regularizer's (depth, normal) weights on this clip
    data: ClipTensors | None = None
    image_loss: losses.CoveredPhotometric | None = None

    @property
    def total(self) -> int:
        return self.cfg.train.static_steps + self.cfg.train.dynamic_steps


def fit(
    clip: TrainingClip,
    cfg,
    *,
    seed: int = 0,
    workdir: Path | None = None,
    progress: bool = True,
    device: torch.device | str | None = None,
    log=None,
) -> tuple[LMGSModel, FitReport]:
    """Train the reference model on a clip (the subject's training split).

    Args:
        clip: frames, cameras, audio, landmarks and optional geometry.
        cfg: an :class:`~lmgs.presets.LMGSConfig`.
        seed: seeds every random choice (frame order, initialisation, densification).
        workdir: where checkpoints and the training curve go (``curve.csv``, and ``curve.png`` when
            matplotlib is installed); a run resumes from there.
        progress: show a progress bar with loss and PSNR.
        device: torch device (default: chosen by :func:`lmgs.device.choose_device`).
        log: optional callable receiving one line of text per stage.

    Returns:
        The trained model and a :class:`FitReport`.
    """
    run = _start(clip, cfg, seed, workdir, device, log)
    _build_model(run, seed)
    _fit_landmarks(run, seed)
    _prepare(run, progress)
    order = np.random.default_rng(seed).integers(0, len(clip), size=run.total)
    for step in range(run.start, run.total):
        _step(run, step, int(order[step]))
    return run.model, _finish(run)


def _start(clip: TrainingClip, cfg, seed: int, workdir, device, log) -> _Run:
    """The device, torch seeded, the clip checked, and its audio features (windows ``[T, W, C]``)."""
    from lmgs.device import choose_device

    dev = choose_device(str(device) if device is not None else None)
    t_start = time.perf_counter()
    torch.manual_seed(seed)
    n = len(clip)
    if n < 8:
        raise InputError(f"training clip has {n} frames; at least 8 are needed")
    from lmgs.audio import compute_features, frontend_from_array

    if cfg.audio.frontend in ("logmel", "mfcc"):
        feats_np = compute_features(clip.audio, 16000, cfg.audio, n_frames=n)
    else:
        if not clip.audio_features or cfg.audio.frontend not in clip.audio_features:
            raise InputError(f"audio front end '{cfg.audio.frontend}' needs precomputed features the subject does not have "
                             f"(in the ER-NeRF / TalkingGaussian layout: aud_{cfg.audio.frontend}.npy)")
        feats_np = frontend_from_array(cfg.audio.frontend, clip.audio_features[cfg.audio.frontend])
    feats = torch.from_numpy(np.ascontiguousarray(feats_np, dtype=np.float32)).to(dev)
    return _Run(clip, cfg, dev, log or (lambda s: None), workdir, t_start, feats)


def _build_model(run: _Run, seed: int) -> None:
    """The scene-derived Gaussian budget, the initial face and mouth Gaussians, and the model."""
    clip, cfg, t, feats = run.clip, run.cfg, run.cfg.train, run.feats
    area = face_area_px(clip)
    run.budget = budget = budget_from_face_area(area, t.budget_density)
    run.n_mouth = n_mouth = max(64, int(budget * t.mouth_fraction))
    face = init_face(clip, max(200, int((budget - n_mouth) * 0.6)), seed)
    mouth = init_mouth(clip, n_mouth, seed) if clip.landmarks3d is not None else init_mouth_fallback(face, n_mouth)
    box_min, box_max, run.extent = scene_box(face)
    build = {
        "in_channels": int(feats.shape[2]), "window": int(feats.shape[1]), "box_min": box_min, "box_max": box_max,
        "intrinsics": [clip.focal, clip.cx, clip.cy, clip.width, clip.height],
        "n_train_frames": len(clip), "bg_shape": [clip.height, clip.width, 3],
    }
    model = LMGSModel(cfg, face, mouth, build["in_channels"], build["window"], build["box_min"], build["box_max"], build["intrinsics"])
    model._build_args = build
    model.train_w2c = torch.from_numpy(np.asarray(clip.w2c, np.float32))
    model.default_background = torch.from_numpy(clip.backgrounds.astype(np.float32).mean(0) / 255.0)
    run.model = model = model.to(run.dev)
    model.audio_net.encoder.fit_normalization(feats)
    run.say(f"budget {budget} Gaussians from a face area of {area:.0f} px; start {len(face)} face + {len(mouth)} mouth")


def _fit_landmarks(run: _Run, seed: int) -> None:
    """Audio-to-landmark stand-in (GeneFace's pretrained model cannot be had here), when SE or LC read landmarks."""
    model, clip, feats, t = run.model, run.clip, run.feats, run.cfg.train
    if not model.uses_landmarks:
        return
    from lmgs.landmarks import cross_fit_landmarks, fit_landmark_predictor, lift_2d_landmarks, max_folds

    a = time.perf_counter()
    targets = clip.landmarks3d
    if targets is None:
        if clip.landmarks2d is None:
            raise InputError("SE/LC need landmarks: the subject has neither 3D nor 2D landmarks")
        c2w = np.linalg.inv(clip.w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])
        targets = lift_2d_landmarks(clip.landmarks2d, c2w, clip.focal, clip.cx, clip.cy)
    targets = torch.as_tensor(np.asarray(targets), dtype=torch.float32)
    model.predictor = fit_landmark_predictor(feats, targets, steps=t.landmark_steps, seed=seed)
    # Training landmarks of held-out quality (see cross_fit_landmarks); a clip too short
    # for the folds (fewer than 8 frames a block) takes fewer, or in-sample predictions.
    n = len(clip)
    folds = min(t.landmark_folds, max_folds(n))
    if folds >= 2:
        run.lms_pred = cross_fit_landmarks(feats, targets, folds=folds, steps=t.landmark_steps, seed=seed).to(run.dev)
    else:
        run.lms_pred = model.predictor.predict(feats).to(run.dev)
    if t.landmark_source != "subject":  # the mouth from the generic lip model, retargeted to this subject
        from lmgs.lips import retarget_for

        model.lips = retarget_for(t.landmark_source, clip.audio, n, targets.numpy(), seed, weights=t.lip_weights)
        run.lms_pred = model.lips.replace_mouth(run.lms_pred, clip.audio, n)
    if run.cfg.guidance.mouth_state:  # from the landmarks that guide training, as at test time from the predicted ones
        model.fit_mouth_state(run.lms_pred)
        run.mouth_states = model.mouth_states(run.lms_pred)
    run.t_lms = time.perf_counter() - a
    how = f"{folds}-fold out-of-fold" if folds >= 2 else "in-sample"
    if model.lips is not None:
        how += f"; mouth (48-67) from the generic lip model ({t.landmark_source}, {t.lip_weights})"
    if t.landmark_folds and folds < 2:
        how += f" ({n} frames are too few for {t.landmark_folds} folds)"
    run.say(f"landmark predictor fitted in {run.t_lms:.1f} s; training landmarks {how}")


def _prepare(run: _Run, progress: bool) -> None:
    """Optimisers and densification (a budget per branch), resuming from a checkpoint of the same
    config in ``workdir``, the progress bar, and what the loss reads besides the frames."""
    model, t, dev, clip = run.model, run.cfg.train, run.dev, run.clip
    run.g_opt = gaussian_adam((model.face, model.mouth), t)
    run.n_opt = network_adamw((model.audio_net, model.face_deform, model.mouth_deform), t.lr_nets)
    stop = int(run.total * t.densify_until)
    run.strategies = (Strategy(start=t.densify_every, stop=stop, every=t.densify_every, budget=run.budget - run.n_mouth),
                      Strategy(start=t.densify_every, stop=stop, every=t.densify_every, budget=run.n_mouth * 2))
    run.ckpt = Path(run.workdir) / "checkpoint.pt" if run.workdir else None
    if run.ckpt is not None and run.ckpt.exists():
        run.start, run.prior = resume(run.ckpt, model, run.g_opt, run.n_opt, run.cfg, dev, run.curve_rows)
        run.t_start -= run.prior  # the clock (curve, report) counts the earlier runs' training too
        run.say(f"resumed from {run.ckpt} at step {run.start}")
    run.states = (initialize_state(len(model.face), dev), initialize_state(len(model.mouth), dev))
    run.saved_at = run.start
    if progress:
        from tqdm import tqdm

        run.bar = tqdm(total=run.total, initial=run.start, desc="lmgs fit", unit="step", leave=False)
    run.lip_boxes = _lip_boxes(clip)
    run.use_geo = run.cfg.gr and clip.depth is not None and clip.normal is not None
    run.prior_weights = prior_weights(run.cfg.train, clip.priors_derived)
    run.data = ClipTensors(clip, dev)
    run.image_loss = losses.CoveredPhotometric(t.lambda_dssim)


def _frame_loss(run: _Run, step: int, i: int, dynamic: bool):
    """Render training frame ``i`` and its loss: L1 + D-SSIM, and in the dynamic stage the mouth
    term, the Geometry Regularizer and the lips' L1 where they apply. Returns ``(render, gt, loss)``."""
    model, clip, t, data = run.model, run.clip, run.cfg.train, run.data
    gt = data.frame(i)
    bg = data.background(i)
    audio = model.audio_net(run.feats, index=data.index(i))[0] if dynamic else None
    lm = run.lms_pred[i] if (dynamic and run.lms_pred is not None) else None
    on_host = run.dev.type == "cpu"  # on a GPU nothing in the step reads a value back (see lmgs.clipdata)
    state = run.mouth_states[i] if (dynamic and run.mouth_states is not None) else None
    r = model.render_frame(model.train_w2c[i], bg, dynamic=dynamic, audio=audio, landmarks=lm, blink=data.blink(i), mouth=state,
                           check_values=on_host)
    loss = run.image_loss(r.rgb, gt, bg, r.head_alpha[..., 0] > 0, i)  # L1 + D-SSIM, over the box around the head
    mouth_px = data.mouth_pixels(i) if dynamic else None
    if mouth_px is not None:
        loss = loss + t.lambda_mouth * r.face_alpha[..., 0].reshape(-1)[mouth_px].mean()
    if run.use_geo and dynamic:
        ramp = gr_ramp(step - t.static_steps, t.gr_warmup)
        w_depth, w_normal = run.prior_weights
        loss = loss + losses.geometry(r.depth, r.normal, r.face_alpha, data.depth(i), data.normal(i) if w_normal else None,
                                      ramp * w_depth, ramp * w_normal, t.normal_reduce, gather=on_host)
    if run.lip_boxes is not None and dynamic and t.lambda_lips > 0:
        y0, y1, x0, x1 = run.lip_boxes[i]
        loss = loss + t.lambda_lips * (r.rgb[y0:y1, x0:x1] - gt[y0:y1, x0:x1]).abs().mean()
    return r, gt, loss


def _stop_if_failed(run: _Run, step: int, i: int, dynamic: bool, loss_value: float, r, gt) -> None:
    """Raise :class:`TrainingDiverged` on a non-finite loss or a collapse (:class:`CollapseGuard`),
    naming the last good checkpoint and writing the curve up to this step."""
    ckpt, workdir = run.ckpt, run.workdir
    finite = math.isfinite(loss_value)
    ratio = run.guard.update(loss_value, "dynamic" if dynamic else "static") if finite else None
    if finite and ratio is None:
        return
    if run.bar is not None:
        run.bar.close()
    if not finite:
        where = f"; the last good checkpoint is {ckpt}" if ckpt is not None and ckpt.exists() else ""
    else:
        where = ""
        if ckpt is not None and ckpt.exists():
            where = f"; the last checkpoint (step {run.saved_at}) is {ckpt}"
            if step - run.saved_at < run.guard.window:
                where += f" (written less than {run.guard.window} steps before: it may already hold the collapse)"
    if workdir is not None:
        drawn = write_failed_curve(workdir, run.curve_rows, step, dynamic, loss_value, r, gt)
        where += f"; the training curve up to it is {drawn}"
    if not finite:
        raise TrainingDiverged(f"loss became non-finite at step {step} (frame {i}){where}")
    raise TrainingDiverged(
        f"training collapsed at step {step} ({'dynamic' if dynamic else 'static'} stage): the mean loss of the last "
        f"{run.guard.window} steps is {ratio:.1f}x the lowest earlier in the stage (training PSNR {psnr(r.rgb.detach(), gt):.1f} dB)"
        f"{where}; try another seed or a smaller budget")


def _step(run: _Run, step: int, i: int) -> None:
    """One training step on frame ``i``: loss, the checks, the optimiser and densification step, the
    curve every 25 steps, a checkpoint every ``checkpoint_every``."""
    model, clip, t = run.model, run.clip, run.cfg.train
    dynamic = step >= t.static_steps
    r, gt, loss = _frame_loss(run, step, i, dynamic)
    loss_value = float(loss.detach())  # one device sync per step, shared by the checks and the curve
    _stop_if_failed(run, step, i, dynamic, loss_value, r, gt)
    optimise(loss, run.g_opt, run.n_opt, dynamic, (model.face, model.mouth))
    (face_strategy, mouth_strategy), (face_state, mouth_state) = run.strategies, run.states
    densify([(face_strategy, model.face, face_state, r.face_means2d, r.face_visible),
             (mouth_strategy, model.mouth, mouth_state, r.mouth_means2d, r.mouth_visible)],
            run.g_opt, step + 1, run.extent, clip.width, clip.height)
    if step % 25 == 0 or step == run.total - 1:
        run.last_psnr = psnr(r.rgb.detach(), gt)
        frac = float(r.se_fraction)
        if not np.isnan(frac):
            run.last_frac = frac
        run.curve_rows.append({"step": step, "stage": "dynamic" if dynamic else "static", "loss": loss_value,
                               "psnr": run.last_psnr, "n_face": len(model.face), "n_mouth": len(model.mouth),
                               "se_fraction": frac, "seconds": time.perf_counter() - run.t_start})
        if run.bar is not None:
            run.bar.set_postfix(loss=f"{loss_value:.4f}", psnr=f"{run.last_psnr:.2f}", n=model.n_gaussians())
    if run.bar is not None:
        run.bar.update(1)
    if run.ckpt is not None and (step + 1) % t.checkpoint_every == 0 and step + 1 < run.total:
        save_checkpoint(run.ckpt, model, run.g_opt, run.n_opt, step + 1, run.curve_rows, time.perf_counter() - run.t_start)
        run.saved_at = step + 1


def _finish(run: _Run) -> FitReport:
    """The report; the curve written and the checkpoint removed (the caller saves the model)."""
    if run.bar is not None:
        run.bar.close()
    seconds = time.perf_counter() - run.t_start
    report = FitReport(run.total - run.start, seconds, run.model.n_gaussians(), run.budget, run.last_psnr, run.last_frac,
                       run.start, run.t_lms, run.curve_rows, prior_seconds=run.prior)
    if run.workdir is not None:
        drawn = write_curve(Path(run.workdir), run.curve_rows)
        if drawn is not None and drawn.suffix == ".csv":
            run.say(f"training curve written to {drawn}; no plot: matplotlib is not installed (pip install 'lmgs[eval]')")
        if run.ckpt is not None and run.ckpt.exists():
            run.ckpt.unlink()
    return report


def gr_ramp(dynamic_step: int, warmup: int) -> float:
    """Weight factor of the Geometry Regularizer at step ``dynamic_step`` (0-based) of the dynamic stage."""
    return 1.0 if warmup <= 0 else min(1.0, (dynamic_step + 1) / warmup)


def prior_weights(t, derived: bool) -> tuple[float, float]:
    """The Geometry Regularizer's depth and normal weights for a clip's priors: ``lambda_depth`` /
    ``lambda_normal``, times ``derived_depth_weight`` / ``derived_normal_weight`` where the priors are
    derived from the tracking rather than measured."""
    if not derived:
        return float(t.lambda_depth), float(t.lambda_normal)
    return float(t.lambda_depth * t.derived_depth_weight), float(t.lambda_normal * t.derived_normal_weight)


def _lip_boxes(clip: TrainingClip, grow: float = 0.6) -> np.ndarray | None:
    """Per frame ``(y0, y1, x0, x1)`` of the lips' box (landmarks 48-67) grown by ``grow``."""
    if clip.landmarks2d is None:
        return None
    lips = np.asarray(clip.landmarks2d)[:, 48:68]
    lo, hi = lips.min(1), lips.max(1)
    c, half = (lo + hi) / 2, (hi - lo) / 2 * (1 + grow) + 2
    x0 = np.clip(np.floor(c[:, 0] - half[:, 0]), 0, clip.width - 1).astype(int)
    x1 = np.clip(np.ceil(c[:, 0] + half[:, 0]), 1, clip.width).astype(int)
    y0 = np.clip(np.floor(c[:, 1] - half[:, 1]), 0, clip.height - 1).astype(int)
    y1 = np.clip(np.ceil(c[:, 1] + half[:, 1]), 1, clip.height).astype(int)
    return np.stack([y0, np.maximum(y1, y0 + 1), x0, np.maximum(x1, x0 + 1)], 1)


def init_mouth_fallback(face: GaussianSet, n: int) -> GaussianSet:
    """Without 3D landmarks: a small blob at the lower-middle of the face points."""
    pts = face.means.detach()
    c = pts.mean(0)
    c[1] = pts[:, 1].quantile(0.75)
    g = torch.Generator().manual_seed(n)
    p = c + torch.randn(n, 3, generator=g) * (pts.std(0) * 0.1)
    return GaussianSet(p, torch.full((n, 3), 0.3), 0.005)
