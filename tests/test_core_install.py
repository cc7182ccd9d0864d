"""The model library stands alone: ``pip install .`` without extras trains and renders.

OpenCV, matplotlib and the rest of the ``eval`` extra are made unimportable in a fresh
interpreter (``sys.modules[name] = None`` makes ``import name`` raise ImportError), as in
an environment that installed only the core dependencies.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lmgs.init import face_area_px, hull_area
from model_fixtures import synthetic_clip

# Everything the core dependencies (torch, numpy, scipy, tqdm, plyfile, numba) do not bring,
# and the layers above the model library.
NOT_IN_CORE = ("cv2", "matplotlib", "skimage", "PIL", "onnx", "onnxruntime", "dlib", "av", "pandas",
               "lmgs_eval", "baselines")

BLOCK = "import sys\nfor _name in {names!r}:\n    sys.modules[_name] = None\n".format(names=NOT_IN_CORE)

SCRIPT = BLOCK + r"""
import dataclasses, importlib, json, pkgutil
from pathlib import Path
import numpy as np
sys.path.insert(0, sys.argv[1])
import lmgs
skip = {"lmgs.render._gsplat", "lmgs.render._triton", "lmgs.render._triton_projection"}  # CUDA only: gsplat (lmgs[cuda]) and Triton (torch's CUDA builds)
mods = [m.name for m in pkgutil.walk_packages(lmgs.__path__, "lmgs.") if m.name not in skip]
for m in mods:
    importlib.import_module(m)
from lmgs.presets import quick
from lmgs.train import fit
from lmgs.types import DrivingAudio
from model_fixtures import synthetic_clip
clip = synthetic_clip(n=16, size=32)
# no head masks: the Gaussian budget comes from the 2D landmarks' hull (the path that used OpenCV)
import torch
from lmgs.types import Camera
lm2d = np.stack([Camera(torch.from_numpy(w), clip.focal, clip.focal, clip.cx, clip.cy, 32, 32).project(torch.from_numpy(p)).numpy()
                 for w, p in zip(clip.w2c, clip.landmarks3d)]).astype(np.float32)
clip = dataclasses.replace(clip, head_masks=None, landmarks2d=lm2d)
cfg = quick()
cfg = cfg.replace(train=dataclasses.replace(cfg.train, static_steps=20, dynamic_steps=20, landmark_steps=10,
                                            densify_every=10, checkpoint_every=1000))
said = []
work = Path(sys.argv[2])
model, report = fit(clip, cfg, seed=0, progress=False, workdir=work, log=said.append)
frames = model.render(DrivingAudio(audio=clip.audio[: 4 * 640], w2c=clip.w2c[:4]))
print(json.dumps({"modules": len(mods), "steps": report.steps, "budget": report.budget, "shape": list(frames.shape),
                  "dtype": str(frames.dtype), "said": said, "files": sorted(p.name for p in work.iterdir())}))
"""


def test_hull_area_matches_opencv():
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(3)
    clouds = [rng.uniform(0, 512, (68, 2)) for _ in range(10)]
    clouds += [rng.normal(200, 15, (68, 2)), rng.uniform(0, 1, (5, 2)) * 1e-3]
    for pts in clouds:
        want = cv2.contourArea(cv2.convexHull(pts.astype(np.float32)))
        assert hull_area(pts) == pytest.approx(want, rel=1e-9, abs=1e-12)
    line = np.c_[np.arange(10.0), 2 * np.arange(10.0)]  # spans no area
    for pts in (line, np.zeros((68, 2)), np.array([[1.0, 2.0], [3.0, 4.0]])):
        assert hull_area(pts) == cv2.contourArea(cv2.convexHull(pts.astype(np.float32))) == 0.0


def test_face_area_from_landmarks_matches_opencv():
    cv2 = pytest.importorskip("cv2")
    import dataclasses

    clip = synthetic_clip(n=24, size=48)
    rng = np.random.default_rng(0)
    lm2d = rng.uniform(8, 40, (24, 68, 2)).astype(np.float32)
    clip = dataclasses.replace(clip, head_masks=None, landmarks2d=lm2d)
    want = np.mean([cv2.contourArea(cv2.convexHull(l)) for l in lm2d[:: max(1, 24 // 20)]]) * 1.6
    assert face_area_px(clip) == pytest.approx(want, rel=1e-12)


def test_model_library_trains_and_renders_without_the_eval_extra(tmp_path):
    here = Path(__file__).parent
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(here), str(tmp_path)], capture_output=True, text=True,
                       timeout=600, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["modules"] >= 20  # every module of lmgs imported
    assert got["steps"] == 40
    assert got["shape"] == [4, 32, 32, 3] and got["dtype"] == "uint8"
    # the curve is written as CSV; the plot is skipped with a note naming what is missing
    assert "curve.csv" in got["files"] and "curve.png" not in got["files"]
    assert any("matplotlib is not installed" in s for s in got["said"])


def test_blocked_modules_are_really_unimportable():
    """The block above does what the test relies on (otherwise the test above could not fail)."""
    r = subprocess.run([sys.executable, "-c", BLOCK + "import cv2\n"], capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and "ModuleNotFoundError" in r.stderr
    r = subprocess.run([sys.executable, "-c", BLOCK + "import matplotlib.pyplot\n"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode != 0 and "ModuleNotFoundError" in r.stderr
