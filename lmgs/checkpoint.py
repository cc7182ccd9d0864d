"""What a training run of the reference model leaves on disk: the model, checkpoints, the curve.

* :func:`save_model` / :func:`load_model`: a trained model (weights, Gaussian counts, config,
  the landmark predictor's shape), written atomically; loading names the file and what does
  not match.
* :func:`save_checkpoint` / :func:`resume`: a run's state every ``checkpoint_every`` steps
  (model, both optimisers, the curve so far, torch's generator, the seconds trained), from
  which :func:`lmgs.train.fit` resumes a run of the same config hash.
* :func:`write_curve`: the training curve as ``curve.csv`` and, with matplotlib, ``curve.png``.
"""

from __future__ import annotations

import csv
import io
import math
import pickle
from pathlib import Path

import numpy as np
import torch

from lmgs.errors import InputError
from lmgs.gaussians import PARAM_NAMES, GaussianSet
from lmgs.model import LMGSModel
from lmgs.optim import gaussian_adam

CHECKPOINT_VERSION = 1


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1]."""
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
        **({"lips": model.lips.to_state()} if getattr(model, "lips", None) is not None else {}),
        **(extra or {}),
    }


def load_model(path: Path, cfg=None, device: torch.device | str = "cpu") -> LMGSModel:
    """Load a model saved by :func:`save_model`; errors name the file and what does not match."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: checkpoint not found")
    blob = _read_blob(path, device, "not a readable checkpoint ({error})")
    if not isinstance(blob, dict) or blob.get("version") != CHECKPOINT_VERSION:
        raise InputError(f"{path}: not an lmgs checkpoint of version {CHECKPOINT_VERSION}")
    if cfg is not None and blob["config_hash"] != cfg.hash():
        raise InputError(f"{path}: made with config {blob['config_hash']}, asked for {cfg.hash()}")
    from lmgs.presets import config_from_dict

    model = _empty_model(config_from_dict(blob["config"]), blob["sizes"], blob["build"], device)
    if blob.get("predictor_args"):
        from lmgs.landmarks import LandmarkPredictor

        model.predictor = LandmarkPredictor(**blob["predictor_args"]).to(device)
    if blob.get("lips"):
        from lmgs.lips import RetargetedLips

        model.lips = RetargetedLips.from_state(blob["lips"])
    try:
        model.load_state_dict(blob["state"])
    except RuntimeError as exc:
        lines = [l.strip() for l in str(exc).splitlines() if l.strip()]
        raise InputError(f"{path}: weights do not match the model ({'; '.join(lines[1:3])[:300]})") from None
    return model


def _read_blob(path: Path, device, unreadable: str):
    """``torch.load`` of a checkpoint file; a file torch cannot read is an :class:`InputError`: ``path: unreadable``
    with ``{error}`` the exception's class name."""
    try:
        return torch.load(path, map_location=device, weights_only=False)
    except (RuntimeError, EOFError, OSError, ValueError, pickle.UnpicklingError) as exc:
        raise InputError(f"{path}: {unreadable.format(error=exc.__class__.__name__)}") from None


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


def _predictor_args(pred) -> dict:
    return {"in_channels": pred.in_channels, "window": pred.window, "n_components": pred.n_components,
            "hidden": int(pred.temporal[0].in_channels)}


def save_checkpoint(path: Path, model, g_opt, n_opt, step: int, curve_rows, elapsed: float) -> None:
    """Write a run's state at ``step`` (see :func:`resume`)."""
    _atomic_save({**_model_blob(model), "step": step, "g_opt": g_opt.state_dict(), "n_opt": n_opt.state_dict(),
                  "curve": curve_rows, "torch_rng": torch.get_rng_state(), "elapsed": float(elapsed)}, path)


def resume(path: Path, model, g_opt, n_opt, cfg, dev, curve_rows) -> tuple[int, float]:
    """Load a checkpoint of :func:`save_checkpoint` into the model and optimisers (the Gaussians' optimiser
    rebuilt for the saved counts) and extend ``curve_rows``; returns the step to go on from and the
    seconds trained up to it."""
    blob = _read_blob(path, dev, "unreadable checkpoint ({error}); delete it to start over")
    if blob.get("config_hash") != cfg.hash():
        raise InputError(f"{path}: checkpoint of config {blob.get('config_hash')}, not {cfg.hash()}; delete it to start over")
    for name, size in blob["sizes"].items():
        gs = getattr(model, name)
        gs.load_tensors({k: blob["state"][f"{name}.{k}"] for k in PARAM_NAMES})
        assert len(gs) == size
    model.load_state_dict(blob["state"])
    g2 = gaussian_adam((model.face, model.mouth), cfg.train)
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


def write_failed_curve(workdir, rows: list[dict], step: int, dynamic: bool, loss_value: float, r, gt) -> Path | None:
    """The curve of a stopped run, up to the step that stopped it, for the user to look at."""
    last = {"step": step, "stage": "dynamic" if dynamic else "static", "loss": loss_value,
            "psnr": psnr(r.rgb.detach(), gt) if math.isfinite(loss_value) else float("nan"),
            "n_face": rows[-1]["n_face"] if rows else 0, "n_mouth": rows[-1]["n_mouth"] if rows else 0,
            "se_fraction": float(r.se_fraction), "seconds": rows[-1]["seconds"] if rows else 0.0}
    return write_curve(Path(workdir), [*rows, last])


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
