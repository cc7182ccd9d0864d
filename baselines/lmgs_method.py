"""The ``lmgs`` method (and its ablation variants) behind the talking-head protocol."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from baselines.common import ON_FOOTAGE_SOURCE, check_lip_weights, cost_of, generic_mouth_tag
from baselines.protocol import MethodInfo, register
from lmgs.checkpoint import load_model, save_model
from lmgs.config import override
from lmgs.device import choose_device
from lmgs.errors import InputError
from lmgs.presets import components
from lmgs.presets import preset as make_preset
from lmgs.train import fit

LANDMARK_STANDIN = ("audio-to-landmark: a per-subject temporal CNN trained on the training split (GeneFace's pretrained "
                    "model cannot be had offline)")
FRONTEND_STANDINS = {  # front ends computed here in place of the paper's WavLM; precomputed ones are the subject's own
    "logmel": "audio front end: log-mel computed in the project (WavLM cannot be had offline)",
    "mfcc": "audio front end: MFCC computed in the project (WavLM cannot be had offline)",
}


GENERIC_MOUTH_STANDIN = ("mouth landmarks (48-67): the project's generic lip model (lmgs.lips: pretrained on generated "
                         "voices, adapted on about 100 s of real speakers' lip tracks), retargeted to the subject, in place "
                         "of GeneFace's model trained on LRS3")


def generic_mouth_standin(weights: str) -> str:
    """The stand-in line of the generic lip model under ``train.lip_weights`` = ``weights``."""
    from lmgs.lips_weights import DEFAULT, describe_weights

    if weights == DEFAULT:
        return GENERIC_MOUTH_STANDIN
    return (f"mouth landmarks (48-67): the project's generic lip model (lmgs.lips: {describe_weights(weights)}), "
            "retargeted to the subject, in place of GeneFace's model trained on LRS3")


def standins(frontend: str) -> tuple[str, ...]:
    """What stands in for the paper's parts under this audio front end."""
    return tuple(x for x in (FRONTEND_STANDINS.get(frontend), LANDMARK_STANDIN) if x)


# The Geometry Regularizer's form in the toolkit's ``lmgs``: the normal term averaged per face pixel at
# 2DGS's normal weight 0.05, instead of the paper's sum over pixels at 1e-4 (variant ``lmgs-gr-paper``).
# On generator-2 bundled data the paper's form, even ramped in (train.gr_warmup), costs appearance and
# collapsed astronaut seed 2 at step 913; the per-pixel form trained on every run.
GR_PER_PIXEL = {"train.normal_reduce": "mean", "train.lambda_normal": 0.05}

# The Geometry Regularizer on priors derived from the tracking (an ingest's head ellipsoid or face mesh, a
# plain folder's ellipsoid ray-cast at load) rather than measured (the bundled subjects' rendered heads):
# set in the config of a method built for such a subject (baselines.protocol.create_method), so a bundled
# subject's config and hash are untouched.
DERIVED_PRIORS = {"train.derived_normal_weight": 0.0}


def weigh_derived_priors(cfg, derived: bool):
    """``cfg`` with :data:`DERIVED_PRIORS` where the subject's priors are derived and the Geometry Regularizer
    is on (a run's own ``--set`` of the weights, applied after, wins)."""
    return cfg.replace(**DERIVED_PRIORS) if derived and cfg.gr else cfg


# On recorded footage (any subject the bundled generator did not make: an ingested video, a processed folder
# from elsewhere), the landmarks guiding SE and LC take their mouth from the generic lip model (lmgs.lips),
# fine-tuned on the subject's training split, as the paper takes them from GeneFace's pretrained model; the
# deformations read the mouth's state from those landmarks, and the landmarks guiding training are out of fold
# (as wrong as at test time). Set in the config of a method built for such a subject
# (baselines.protocol.create_method); a run's own --set wins (train.landmark_source=subject is the per-subject
# predictor). The bundled subjects keep the per-subject predictor: the generic model was pretrained on the
# generator's own articulation, so they test nothing of it, and their tables were made without it.
# The landmarks guiding training as wrong as at test time: out-of-fold predictions (5 folds) instead of the
# in-sample ones (lmgs.landmarks.cross_fit_landmarks); the variant lmgs-oof, and lmgs on recorded footage.
OUT_OF_FOLD = {"train.landmark_folds": 5}
ON_FOOTAGE = {"guidance.mouth_state": True, "train.landmark_source": ON_FOOTAGE_SOURCE, **OUT_OF_FOLD}


def on_footage(cfg, footage: bool):
    """``cfg`` with :data:`ON_FOOTAGE` where the subject is recorded footage and SE or LC reads the landmarks
    (a variant without both, e.g. ``lmgs-base``, stays as its name says)."""
    return cfg.replace(**ON_FOOTAGE) if footage and (cfg.guidance.se or cfg.guidance.lc) else cfg


# Named variants for Tables III and IV: dotted config changes on the quick preset. Every variant
# with GR on uses the full model's form, so an ablation changes only what its name says.
VARIANTS: dict[str, dict] = {
    "lmgs": {**GR_PER_PIXEL},
    "lmgs-theta0.4": {"guidance.theta": 0.4, **GR_PER_PIXEL},
    "lmgs-theta0.8": {"guidance.theta": 0.8, **GR_PER_PIXEL},
    "lmgs-no-se": {"guidance.se": False, **GR_PER_PIXEL},
    "lmgs-no-lc": {"guidance.lc": False, **GR_PER_PIXEL},
    "lmgs-no-gr": {"gr": False},
    "lmgs-base": {"guidance.se": False, "guidance.lc": False, "gr": False},
    # GR as the paper writes it: the normal term summed over the face's pixels, lambda_N = 1e-4
    # (the quick preset's own TrainConfig), ramped in over train.gr_warmup steps.
    "lmgs-gr-paper": {},
    # Table IV's audio rows: "w/o Audio Encoder" (mean over the window, one linear layer) and
    # "Replacing Audio Net with DS" (the subject's precomputed DeepSpeech features, aud_ds.npy:
    # real ER-NeRF / TalkingGaussian subjects have them, the bundled ones do not).
    "lmgs-no-ae": {"audio.use_encoder": False, **GR_PER_PIXEL},
    "lmgs-ds": {"audio.frontend": "ds", **GR_PER_PIXEL},
    # The per-subject predictor's out-of-fold predictions guiding training (OUT_OF_FOLD).
    "lmgs-oof": {**OUT_OF_FOLD, **GR_PER_PIXEL},
    # SE by θ alone, as the paper writes it, without the cap at the share the paper reports (the default
    # guidance.select_fraction = 0.2): at θ = 0.6 it selected 61-79 % of astronaut's face points, where lmgs
    # did worse than without SE; the records of lmgs before the cap.
    "lmgs-uncapped": {"guidance.select_fraction": 0.0, **GR_PER_PIXEL},
}


def derived_priors_part(cfg) -> str | None:
    """How a config's Geometry Regularizer weighs derived priors, in words (its description); None where it
    weighs them as measured ones, or has no regularizer."""
    t = cfg.train
    if not cfg.gr or (t.derived_depth_weight, t.derived_normal_weight) == (1.0, 1.0):
        return None
    return (f"on priors derived from the tracking the GR's depth term x{t.derived_depth_weight:g}, "
            f"normal term x{t.derived_normal_weight:g}")


def derived_priors_tag(cfg) -> str | None:
    """The display name's word for a config that weighs derived priors apart (None where it does not)."""
    if derived_priors_part(cfg) is None:
        return None
    t = cfg.train
    if (t.derived_depth_weight, t.derived_normal_weight) == (1.0, 0.0):
        return "no normals on derived priors"
    return f"derived priors: depth x{t.derived_depth_weight:g}, normals x{t.derived_normal_weight:g}"


class LMGSMethod:
    """Adapter of :mod:`lmgs` to the toolkit's fit / render / describe protocol."""

    def __init__(self, variant: str = "lmgs", preset: str = "quick", overrides: dict | None = None, device: str | None = None,
                 budget_density: float | None = None, priors_derived: bool = False, footage: bool = False):
        self.variant = variant
        # a subject's knee density (create_method); an explicit --set train.budget_density wins
        density = {} if budget_density is None else {"train.budget_density": float(budget_density)}
        try:
            self.cfg = override(make_preset(preset), {**VARIANTS[variant], **density}, what="variant")
            self.cfg = on_footage(weigh_derived_priors(self.cfg, priors_derived), footage)
            self.cfg = override(self.cfg, overrides or {})
        except InputError:
            raise
        except ValueError as exc:  # a config's own check of a value (e.g. a fraction outside [0, 1])
            raise InputError(f"--set: a value lmgs does not take ({exc})") from None
        check_lip_weights(self.cfg.train.lip_weights, self.cfg.train.landmark_source, "train.")
        self.device = device
        self.model = None
        self.report = None

    def fit(self, clip, *, seed: int, workdir: Path, progress: bool = True) -> None:
        workdir = Path(workdir)
        final = workdir / "model.pt"
        if final.exists():
            self.model = load_model(final, cfg=self.cfg, device=choose_device(self.device))
            self.report = None
            return
        self.model, self.report = fit(clip, self.cfg, seed=seed, workdir=workdir, progress=progress, device=self.device)
        save_model(self.model, final, extra={"fit": {"seconds": self.report.seconds, "steps": self.report.steps,
                                                     "se_fraction": self.report.se_fraction}})

    def render(self, driving, timings: dict | None = None) -> np.ndarray:
        if self.model is None:
            raise RuntimeError("render() before fit()")
        return self.model.render(driving, timings=timings)

    def describe(self) -> MethodInfo:
        g, a = self.cfg.guidance, self.cfg.audio
        t = self.cfg.train
        gr = "no GR" if not self.cfg.gr else f"GR (normal term per-pixel {t.normal_reduce}, weight {t.lambda_normal:g})" \
            if t.normal_reduce != "sum" else f"GR as the paper writes it (normal term summed, weight {t.lambda_normal:g})"
        parts = ["SE" if g.se else "no SE", "LC" if g.lc else "no LC", gr, f"theta={g.theta:g}"]
        if not a.use_encoder:
            parts.append("no Audio Encoder")
        if a.frontend != "logmel":
            parts.append(f"audio front end {a.frontend}")
        if g.se:
            parts.append(f"SE capped at {g.select_fraction:.0%} of the points per frame" if g.select_fraction
                         else "SE by theta alone (no cap on the points selected)")
        if g.mouth_state:
            parts.append("the deformations read the mouth's opening and width from the landmarks")
        if derived_priors_part(self.cfg):
            parts.append(derived_priors_part(self.cfg))
        reads = g.reads_landmarks
        if reads and t.landmark_folds:
            parts.append(f"out-of-fold training landmarks ({t.landmark_folds} folds)")
        generic = None  # the landmark source in the display name, when not the per-subject predictor
        if reads and t.landmark_source != "subject":
            parts.append("mouth landmarks from the generic lip model" + (", fine-tuned on the subject"
                                                                          if t.landmark_source == "generic-tuned" else ""))
            generic = generic_mouth_tag(t.landmark_source)
        derived = derived_priors_tag(self.cfg)
        tags = [x for x in (generic, "mouth state" if g.mouth_state else None, derived) if x]  # in the display name
        return MethodInfo(
            name=self.variant,
            display_name=(f"Ours ({', '.join(['lmgs', *tags])})" if self.variant == "lmgs" else f"lmgs ({', '.join(parts)})"),
            family="3DGS",
            description=(
                "The paper's method on TalkingGaussian's face/mouth decomposition, trained on a CPU schedule "
                f"({self.cfg.train.static_steps} static + {self.cfg.train.dynamic_steps} dynamic steps, preset "
                f"'{self.cfg.preset}'); {', '.join(parts)}"
                + (f"; the landmarks guiding training are out-of-fold predictions ({t.landmark_folds} folds), as wrong "
                   "as at test time, as a pretrained predictor's would be" if reads and t.landmark_folds else "")
                + (f"; the GR weights ramp in over the first {t.gr_warmup} dynamic steps" if self.cfg.gr and t.gr_warmup else "")
                + ("; not the paper's GR form: the normal term per pixel at 2DGS's weight (the paper's sum at 1e-4 "
                   "collapsed training on bundled data)." if self.cfg.gr and t.normal_reduce != "sum" else ".")
            ),
            standins=standins(a.frontend) + ((generic_mouth_standin(t.lip_weights),) if generic is not None else ()),
            config=self.cfg.to_dict(),
            config_hash=self.cfg.hash(),
            variant=None if self.variant == "lmgs" else self.variant.removeprefix("lmgs-"),
            components=components(self.cfg),
        )

    def lip_weights(self) -> str | None:
        """The generic lip model's weights this configuration reads (None where the landmarks come from the
        per-subject predictor, or nothing reads them)."""
        g, t = self.cfg.guidance, self.cfg.train
        return t.lip_weights if g.reads_landmarks and t.landmark_source != "subject" else None

    def cost(self) -> dict:
        if self.model is None:
            return {}
        return cost_of(self.model, self.model.n_gaussians())


for _name in VARIANTS:
    register(_name, scene_budget=True, ablation=_name != "lmgs", reads_priors=True, lip_model=True)(lambda _v=_name, **kw: LMGSMethod(_v, **kw))

