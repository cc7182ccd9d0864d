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
"""

from __future__ import annotations

import csv
import io
import math
import pickle
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from lmgs import losses
from lmgs.errors import InputError, TrainingDiverged  # noqa: F401 (TrainingDiverged re-exported)
from lmgs.gaussians import PARAM_NAMES, GaussianSet
from lmgs.init import face_area_px, init_face, init_mouth
from lmgs.model import LMGSModel, to_image
from lmgs.strategy import Strategy, accumulate, budget_from_face_area, initialize_state, step_post_backward
from lmgs.types import TrainingClip

CHECKPOINT_VERSION = 1
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


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return 10 * np.log10(1.0 / max(mse, 1e-10))


def _atomic_save(obj, path: Path) -> None:
    from lmgs.fileio import atomic_path

    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def save_model(model: LMGSModel, path: Path, extra: dict | None = None) -> None:
    """Save a model (weights, Gaussian counts, config) atomically."""
    _atomic_save(_model_blob(model, extra), Path(path))


def _model_blob(model: LMGSModel, extra: dict | None = None) -> dict:
    return {
        "version": CHECKPOINT_VERSION,
        "config": model.cfg.to_dict(),
        "config_hash": model.cfg.hash(),
        "sizes": {"face": len(model.face), "mouth": len(model.mouth)},
        "build": model._build_args,
        "state": model.state_dict(),
        "predictor_args": None if model.predictor is None else _predictor_args(model.predictor),
        **(extra or {}),
    }


def load_model(path: Path, cfg=None, device: torch.device | str = "cpu") -> LMGSModel:
    """Load a model saved by :func:`save_model`; errors name the file and what does not match."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: checkpoint not found")
    try:
        blob = torch.load(path, map_location=device, weights_only=False)
    except (RuntimeError, EOFError, OSError, ValueError, pickle.UnpicklingError) as exc:
        raise InputError(f"{path}: not a readable checkpoint ({exc.__class__.__name__})") from None
    if not isinstance(blob, dict) or blob.get("version") != CHECKPOINT_VERSION:
        raise InputError(f"{path}: not an lmgs checkpoint of version {CHECKPOINT_VERSION}")
    if cfg is not None and blob["config_hash"] != cfg.hash():
        raise InputError(f"{path}: made with config {blob['config_hash']}, asked for {cfg.hash()}")
    from lmgs.presets import config_from_dict

    model = _empty_model(config_from_dict(blob["config"]), blob["sizes"], blob["build"], device)
    if blob.get("predictor_args"):
        from lmgs.landmarks import LandmarkPredictor

        model.predictor = LandmarkPredictor(**blob["predictor_args"]).to(device)
    try:
        model.load_state_dict(blob["state"])
    except RuntimeError as exc:
        lines = [l.strip() for l in str(exc).splitlines() if l.strip()]
        raise InputError(f"{path}: weights do not match the model ({'; '.join(lines[1:3])[:300]})") from None
    return model


def _empty_model(cfg, sizes: dict, build: dict, device) -> LMGSModel:
    face = GaussianSet(torch.zeros(sizes["face"], 3), torch.full((sizes["face"], 3), 0.5), 0.01)
    mouth = GaussianSet(torch.zeros(sizes["mouth"], 3), torch.full((sizes["mouth"], 3), 0.5), 0.01)
    model = LMGSModel(cfg, face, mouth, build["in_channels"], build["window"], build["box_min"], build["box_max"], build["intrinsics"])
    model._build_args = build
    if build.get("n_train_frames"):
        model.train_w2c = torch.zeros(build["n_train_frames"], 4, 4)
    if build.get("bg_shape"):
        model.default_background = torch.zeros(*build["bg_shape"])
    return model.to(device)


def _optimizers(model: LMGSModel, cfg) -> tuple[torch.optim.Optimizer, torch.optim.Optimizer]:
    t = cfg.train
    rates = {"means": t.lr_means, "quats": t.lr_quats, "log_scales": t.lr_scales, "opacity_logits": t.lr_opacity, "color_logits": t.lr_colors}
    groups = []
    for branch in (model.face, model.mouth):
        for name in PARAM_NAMES:
            groups.append({"params": [getattr(branch, name)], "lr": rates[name], "name": name})
    g_opt = torch.optim.Adam(groups, eps=1e-15)
    nets = [p for m in (model.audio_net, model.face_deform, model.mouth_deform) for p in m.parameters()]
    n_opt = torch.optim.AdamW(nets, lr=t.lr_nets, weight_decay=1e-4)
    return g_opt, n_opt


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
    from lmgs.device import choose_device

    dev = choose_device(str(device) if device is not None else None)
    say = log or (lambda s: None)
    t_start = time.perf_counter()
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    n = len(clip)
    if n < 8:
        raise InputError(f"training clip has {n} frames; at least 8 are needed")
    t = cfg.train

    # Audio windows and their normalisation.
    from lmgs.audio import compute_features, frontend_from_array

    if cfg.audio.frontend in ("logmel", "mfcc"):
        feats_np = compute_features(clip.audio, 16000, cfg.audio, n_frames=n)
    else:
        if not clip.audio_features or cfg.audio.frontend not in clip.audio_features:
            raise InputError(f"audio front end '{cfg.audio.frontend}' needs precomputed features the subject does not have "
                             f"(in the ER-NeRF / TalkingGaussian layout: aud_{cfg.audio.frontend}.npy)")
        feats_np = frontend_from_array(cfg.audio.frontend, clip.audio_features[cfg.audio.frontend])
    feats = torch.from_numpy(np.ascontiguousarray(feats_np, dtype=np.float32)).to(dev)

    # Scene-derived budget and initial Gaussians.
    area = face_area_px(clip)
    budget = budget_from_face_area(area, t.budget_density)
    n_mouth = max(64, int(budget * t.mouth_fraction))
    n_face0 = max(200, int((budget - n_mouth) * 0.6))
    face = init_face(clip, n_face0, seed)
    mouth = init_mouth(clip, n_mouth, seed) if clip.landmarks3d is not None else init_mouth_fallback(face, n_mouth)
    pts = face.means.detach()
    lo, hi = pts.min(0).values, pts.max(0).values
    margin = (hi - lo) * 0.25 + 1e-3
    build = {
        "in_channels": int(feats.shape[2]), "window": int(feats.shape[1]),
        "box_min": (lo - margin).tolist(), "box_max": (hi + margin).tolist(),
        "intrinsics": [clip.focal, clip.cx, clip.cy, clip.width, clip.height],
        "n_train_frames": n, "bg_shape": [clip.height, clip.width, 3],
    }
    model = LMGSModel(cfg, face, mouth, build["in_channels"], build["window"], build["box_min"], build["box_max"], build["intrinsics"])
    model._build_args = build
    model.train_w2c = torch.from_numpy(np.asarray(clip.w2c, np.float32))
    model.default_background = torch.from_numpy(clip.backgrounds.astype(np.float32).mean(0) / 255.0)
    model = model.to(dev)
    model.audio_net.encoder.fit_normalization(feats)
    say(f"budget {budget} Gaussians from a face area of {area:.0f} px; start {len(face)} face + {len(mouth)} mouth")

    # Audio-to-landmark stand-in (GeneFace's pretrained model cannot be had here).
    lms_pred = None
    t_lms = 0.0
    if model.uses_landmarks:
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
        folds = min(t.landmark_folds, max_folds(n))
        if folds >= 2:
            lms_pred = cross_fit_landmarks(feats, targets, folds=folds, steps=t.landmark_steps, seed=seed).to(dev)
        else:
            lms_pred = model.predictor.predict(feats).to(dev)
        t_lms = time.perf_counter() - a
        how = f"{folds}-fold out-of-fold" if folds >= 2 else "in-sample"
        if t.landmark_folds and folds < 2:
            how += f" ({n} frames are too few for {t.landmark_folds} folds)"
        say(f"landmark predictor fitted in {t_lms:.1f} s; training landmarks {how}")

    g_opt, n_opt = _optimizers(model, cfg)
    total = t.static_steps + t.dynamic_steps
    densify_stop = int(total * t.densify_until)
    face_strategy = Strategy(start=t.densify_every, stop=densify_stop, every=t.densify_every, budget=budget - n_mouth)
    mouth_strategy = Strategy(start=t.densify_every, stop=densify_stop, every=t.densify_every, budget=n_mouth * 2)
    face_state = initialize_state(len(model.face), dev)
    mouth_state = initialize_state(len(model.mouth), dev)
    extent = float((hi - lo).norm())

    ckpt = Path(workdir) / "checkpoint.pt" if workdir else None
    curve_rows: list[dict] = []
    start, prior = 0, 0.0
    if ckpt is not None and ckpt.exists():
        start, prior = _resume(ckpt, model, g_opt, n_opt, cfg, dev, curve_rows)
        t_start -= prior  # the clock (curve, report) counts the earlier runs' training too
        face_state = initialize_state(len(model.face), dev)
        mouth_state = initialize_state(len(model.mouth), dev)
        say(f"resumed from {ckpt} at step {start}")
    order = rng.integers(0, n, size=total)

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, initial=start, desc="lmgs fit", unit="step", leave=False)
    last_psnr, last_frac = float("nan"), float("nan")
    mouth_masks = clip.mouth_masks
    lip_boxes = _lip_boxes(clip)
    use_geo = cfg.gr and clip.depth is not None and clip.normal is not None
    guard = CollapseGuard()
    saved_at = start
    for step in range(start, total):
        i = int(order[step])
        dynamic = step >= t.static_steps
        gt = to_image(clip.frames[i], dev)
        bg = to_image(clip.background(i), dev)
        w2c = model.train_w2c[i]
        audio = model.audio_net(feats, index=torch.tensor([i], device=dev))[0] if dynamic else None
        lm = lms_pred[i] if (dynamic and lms_pred is not None) else None
        r = model.render_frame(w2c, bg, dynamic=dynamic, audio=audio, landmarks=lm, blink=float(clip.blink[i]))
        loss = losses.photometric(r.rgb, gt, t.lambda_dssim)
        if mouth_masks is not None and dynamic:
            m = torch.from_numpy(mouth_masks[i]).to(dev)
            if m.any():
                loss = loss + t.lambda_mouth * r.face_alpha[..., 0][m].mean()
        if use_geo and dynamic:
            ref_d = torch.from_numpy(clip.depth[i].astype(np.float32)).to(dev)
            ref_n = torch.from_numpy(clip.normal[i].astype(np.float32) / 127.0).to(dev)
            ramp = gr_ramp(step - t.static_steps, t.gr_warmup)
            loss = loss + losses.geometry(r.depth, r.normal, r.face_alpha, ref_d, ref_n, ramp * t.lambda_depth,
                                          ramp * t.lambda_normal, t.normal_reduce)
        if lip_boxes is not None and dynamic and t.lambda_lips > 0:
            y0, y1, x0, x1 = lip_boxes[i]
            loss = loss + t.lambda_lips * (r.rgb[y0:y1, x0:x1] - gt[y0:y1, x0:x1]).abs().mean()
        loss_value = float(loss.detach())  # one device sync per step, shared by the checks and the curve
        if not math.isfinite(loss_value):
            if bar is not None:
                bar.close()
            where = f"; the last good checkpoint is {ckpt}" if ckpt is not None and ckpt.exists() else ""
            if workdir is not None:
                drawn = _write_failed_curve(workdir, curve_rows, step, dynamic, loss_value, r, gt)
                where += f"; the training curve up to it is {drawn}"
            raise TrainingDiverged(f"loss became non-finite at step {step} (frame {i}){where}")
        ratio = guard.update(loss_value, "dynamic" if dynamic else "static")
        if ratio is not None:
            if bar is not None:
                bar.close()
            where = ""
            if ckpt is not None and ckpt.exists():
                where = f"; the last checkpoint (step {saved_at}) is {ckpt}"
                if step - saved_at < guard.window:
                    where += f" (written less than {guard.window} steps before: it may already hold the collapse)"
            if workdir is not None:
                drawn = _write_failed_curve(workdir, curve_rows, step, dynamic, loss_value, r, gt)
                where += f"; the training curve up to it is {drawn}"
            raise TrainingDiverged(
                f"training collapsed at step {step} ({'dynamic' if dynamic else 'static'} stage): the mean loss of the last "
                f"{guard.window} steps is {ratio:.1f}x the lowest earlier in the stage (training PSNR {_psnr(r.rgb.detach(), gt):.1f} dB)"
                f"{where}; try another seed or a smaller budget")
        g_opt.zero_grad(set_to_none=True)
        n_opt.zero_grad(set_to_none=True)
        loss.backward()
        g_opt.step()
        if dynamic:
            n_opt.step()
        with torch.no_grad():
            for gs in (model.face, model.mouth):
                gs.quats.data = torch.nn.functional.normalize(gs.quats.data, dim=-1)
        accumulate(face_state, r.face_means2d, r.face_visible, clip.width, clip.height)
        accumulate(mouth_state, r.mouth_means2d, r.mouth_visible, clip.width, clip.height)
        step_post_backward(face_strategy, model.face, g_opt, face_state, step + 1, extent)
        step_post_backward(mouth_strategy, model.mouth, g_opt, mouth_state, step + 1, extent)
        if step % 25 == 0 or step == total - 1:
            last_psnr = _psnr(r.rgb.detach(), gt)
            if not np.isnan(r.se_fraction):
                last_frac = r.se_fraction
            curve_rows.append({"step": step, "stage": "dynamic" if dynamic else "static", "loss": loss_value, "psnr": last_psnr,
                               "n_face": len(model.face), "n_mouth": len(model.mouth), "se_fraction": r.se_fraction,
                               "seconds": time.perf_counter() - t_start})
            if bar is not None:
                bar.set_postfix(loss=f"{loss_value:.4f}", psnr=f"{last_psnr:.2f}", n=model.n_gaussians())
        if bar is not None:
            bar.update(1)
        if ckpt is not None and (step + 1) % t.checkpoint_every == 0 and step + 1 < total:
            _save_checkpoint(ckpt, model, g_opt, n_opt, step + 1, curve_rows, time.perf_counter() - t_start)
            saved_at = step + 1
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - t_start
    report = FitReport(total - start, seconds, model.n_gaussians(), budget, last_psnr, last_frac, start, t_lms, curve_rows,
                       prior_seconds=prior)
    if workdir is not None:
        drawn = write_curve(Path(workdir), curve_rows)
        if drawn is not None and drawn.suffix == ".csv":
            say(f"training curve written to {drawn}; no plot: matplotlib is not installed (pip install 'lmgs[eval]')")
        if ckpt is not None and ckpt.exists():
            ckpt.unlink()
    return model, report


def _write_failed_curve(workdir, rows: list[dict], step: int, dynamic: bool, loss_value: float, r, gt) -> Path | None:
    """The curve of a stopped run, up to the step that stopped it, for the user to look at."""
    last = {"step": step, "stage": "dynamic" if dynamic else "static", "loss": loss_value,
            "psnr": _psnr(r.rgb.detach(), gt) if math.isfinite(loss_value) else float("nan"),
            "n_face": rows[-1]["n_face"] if rows else 0, "n_mouth": rows[-1]["n_mouth"] if rows else 0,
            "se_fraction": r.se_fraction, "seconds": rows[-1]["seconds"] if rows else 0.0}
    return write_curve(Path(workdir), [*rows, last])


def gr_ramp(dynamic_step: int, warmup: int) -> float:
    """Weight factor of the Geometry Regularizer at step ``dynamic_step`` (0-based) of the dynamic stage."""
    return 1.0 if warmup <= 0 else min(1.0, (dynamic_step + 1) / warmup)


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


def _predictor_args(pred) -> dict:
    return {"in_channels": pred.in_channels, "window": pred.window, "n_components": pred.n_components,
            "hidden": int(pred.temporal[0].in_channels)}


def _save_checkpoint(path: Path, model, g_opt, n_opt, step: int, curve_rows, elapsed: float) -> None:
    _atomic_save({**_model_blob(model), "step": step, "g_opt": g_opt.state_dict(), "n_opt": n_opt.state_dict(),
                  "curve": curve_rows, "torch_rng": torch.get_rng_state(), "elapsed": float(elapsed)}, path)


def _resume(path: Path, model, g_opt, n_opt, cfg, dev, curve_rows) -> int:
    try:
        blob = torch.load(path, map_location=dev, weights_only=False)
    except (RuntimeError, EOFError, OSError, ValueError, pickle.UnpicklingError) as exc:
        raise InputError(f"{path}: unreadable checkpoint ({exc.__class__.__name__}); delete it to start over") from None
    if blob.get("config_hash") != cfg.hash():
        raise InputError(f"{path}: checkpoint of config {blob.get('config_hash')}, not {cfg.hash()}; delete it to start over")
    for name, size in blob["sizes"].items():
        gs = getattr(model, name)
        gs.load_tensors({k: blob["state"][f"{name}.{k}"] for k in PARAM_NAMES})
        assert len(gs) == size
    model.load_state_dict(blob["state"])
    g2, n2 = _optimizers(model, cfg)
    g_opt.param_groups.clear()
    g_opt.state.clear()
    for grp in g2.param_groups:
        g_opt.add_param_group(grp)
    g_opt.load_state_dict(blob["g_opt"])
    n_opt.load_state_dict(blob["n_opt"])
    torch.set_rng_state(blob["torch_rng"])
    curve_rows.extend(blob.get("curve", []))
    # seconds of training up to the checkpoint (older checkpoints: the curve's last timestamp)
    elapsed = blob.get("elapsed", curve_rows[-1]["seconds"] if curve_rows else 0.0)
    return int(blob["step"]), float(elapsed)


def write_curve(workdir: Path, rows: list[dict]) -> Path | None:
    """The training curve as CSV, and as a PNG plot (loss and PSNR against step) when matplotlib is there.

    matplotlib is not a dependency of the model library (it comes with ``pip install 'lmgs[eval]'``):
    without it only ``curve.csv`` is written.

    Returns:
        The plot's path, the CSV's when matplotlib is missing, or None when there are no rows.
    """
    if not rows:
        return None
    workdir.mkdir(parents=True, exist_ok=True)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    (workdir / "curve.csv").write_text(buf.getvalue())
    try:
        import matplotlib
    except ImportError:
        return workdir / "curve.csv"

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(8, 3))
    steps = [r["step"] for r in rows]
    ax[0].plot(steps, [r["loss"] for r in rows])
    ax[0].set(xlabel="step", ylabel="loss", yscale="log")
    ax[1].plot(steps, [r["psnr"] for r in rows])
    ax[1].set(xlabel="step", ylabel="PSNR (dB, training frame)")
    fig.tight_layout()
    fig.savefig(workdir / "curve.png", dpi=90)
    plt.close(fig)
    return workdir / "curve.png"
