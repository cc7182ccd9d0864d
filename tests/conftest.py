"""Shared fixtures: a small hand-made folder in the ER-NeRF/TalkingGaussian layout, the bundled
subject the ingest tests read, and the checks of a command's one-line error."""

from __future__ import annotations

import os

# Before torch or numba load (see lmgs/__init__.py): idle OpenMP pools must not spin.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import json
import wave
from pathlib import Path

import numpy as np
import pytest

# Keep tests off the user's cache: every test run gets its own data root and cache. Session-scoped,
# so that module-scoped fixtures (set up before any function-scoped one) are isolated too.
@pytest.fixture(autouse=True, scope="session")
def _isolated_cache(tmp_path_factory):
    base = tmp_path_factory.getbasetemp() / "cache"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("XDG_CACHE_HOME", str(base))
        mp.setenv("LMGS_DATA", str(base / "data"))
        yield


@pytest.fixture(scope="module")
def one_thread():
    """torch and numba on one thread for a module's tests (``pytestmark = pytest.mark.usefixtures("one_thread")``):
    frames of tens of pixels gain nothing from threads, and on shared cores extra threads only wait."""
    import numba
    import torch

    before = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    yield
    torch.set_num_threads(before[0])
    numba.set_num_threads(before[1])


def write_pcm_wav(path: Path, x: np.ndarray, sr: int) -> None:
    """Write float audio ``[S]`` or ``[S, C]`` as 16-bit PCM with the stdlib (an outside writer)."""
    x = np.asarray(x, np.float64)
    if x.ndim == 1:
        x = x[:, None]
    pcm = np.clip(np.rint(x * 32767), -32768, 32767).astype("<i2")
    with wave.open(str(path), "wb") as w:
        w.setnchannels(x.shape[1])
        w.setsampwidth(2)
        w.setframerate(sr)
        w.writeframes(pcm.tobytes())


ALEXNET_SHAPES = {"features.0": (64, 3, 11, 11), "features.3": (192, 64, 5, 5), "features.6": (384, 192, 3, 3),
                  "features.8": (256, 384, 3, 3), "features.10": (256, 256, 3, 3)}


def random_alexnet_state(seed: int = 0) -> dict:
    """A random state dict in torchvision's alexnet key layout (the real trunk is not on this machine)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    sd = {}
    for k, s in ALEXNET_SHAPES.items():
        fan = s[1] * s[2] * s[3]
        sd[f"{k}.weight"] = torch.randn(s, generator=g) * (2.0 / fan) ** 0.5
        sd[f"{k}.bias"] = torch.zeros(s[0])
    sd["classifier.1.weight"] = torch.zeros(4, 4)  # the classifier is not used: any shape is accepted
    return sd


def make_ernerf_folder(root: Path, n: int = 12, size: int = 32, seed: int = 0) -> dict:
    """Write a tiny subject exactly as ER-NeRF's process.py lays it out; return what was written."""
    import cv2

    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    for sub in ("ori_imgs", "gt_imgs", "torso_imgs", "parsing"):
        (root / sub).mkdir(exist_ok=True)
    lms = rng.uniform(4, size - 4, size=(n, 68, 2)).round(2)
    for i in range(n):
        img = np.full((size, size, 3), 40 + 10 * i, np.uint8)
        cv2.imwrite(str(root / "ori_imgs" / f"{i}.jpg"), img)
        cv2.imwrite(str(root / "gt_imgs" / f"{i}.jpg"), img)
        np.savetxt(root / "ori_imgs" / f"{i}.lms", lms[i], "%f")
    cv2.imwrite(str(root / "bc.jpg"), np.zeros((size, size, 3), np.uint8))
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, 2, 3] = 1.0 + 0.01 * np.arange(n)
    cut = int(n * 10 / 11)
    for fname, ids in (("transforms_train.json", range(cut)), ("transforms_val.json", range(cut, n))):
        d = {"focal_len": 40.0, "cx": size / 2, "cy": size / 2,
             "frames": [{"img_id": i, "aud_id": i, "transform_matrix": c2w[i].tolist()} for i in ids]}
        (root / fname).write_text(json.dumps(d))
    blink = rng.uniform(0, 5, n).round(2)
    header = ["frame", " face_id", " timestamp", " confidence", " success", " AU01_r", " AU25_r", " AU45_r"]
    lines = [",".join(header)]
    for i in range(n):
        lines.append(", ".join(str(v) for v in [i + 1, 0, i * 0.04, 0.98, 1, 0.1, 0.2, blink[i]]))
    (root / "au.csv").write_text("\n".join(lines) + "\n")
    t = np.arange(n * 640) / 16000
    audio = 0.25 * np.sin(2 * np.pi * 220 * t)
    write_pcm_wav(root / "aud.wav", audio, 16000)
    ds = rng.normal(size=(n, 16, 29)).astype(np.float32)
    np.save(root / "aud_ds.npy", ds)
    return {"lms": lms, "c2w": c2w, "blink": blink, "audio": audio, "ds": ds, "cut": cut, "n": n, "size": size}


@pytest.fixture
def ernerf_folder(tmp_path) -> tuple[Path, dict]:
    root = tmp_path / "data" / "tiny"
    return root, make_ernerf_folder(root)


def run_cli(*argv: str) -> tuple[int, str, str]:
    """Run ``lmgs-eval`` in-process; return (exit code, stdout, stderr)."""
    import contextlib
    import io

    from lmgs_eval.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(list(argv))
        except SystemExit as exc:  # argparse errors
            rc = int(exc.code or 0)
    return rc, out.getvalue(), err.getvalue()



def one_line_error(rc: int, out: str, err: str, *words: str) -> str:
    """Exit 2, no traceback, and one error line (progress lines before it, e.g. the subject read, are not errors)."""
    assert rc == 2, (rc, out, err)
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def ingest_error_line(rc: int, err: str, *words: str) -> None:
    """:func:`one_line_error` of ``lmgs-eval ingest``, the line starting with its name."""
    line = one_line_error(rc, "", err, *words)
    assert line.startswith("lmgs-eval ingest: error:"), line


def entries(root: Path) -> list[str]:
    """What a data root holds (nothing half-written may be left there)."""
    return sorted(p.name for p in root.iterdir()) if root.exists() else []


TRUTH_SIZE, TRUTH_SECONDS = 256, 3.0


@pytest.fixture(scope="session")
def truth(tmp_path_factory) -> Path:
    """The bundled astronaut at 256 px for 3 s, built once: the ingest tests read its raw video
    (``astronaut.mp4``) or its frames and hold what they make against the rest."""
    from lmgs_eval.data import bundled

    out = tmp_path_factory.mktemp("truth") / "astronaut"
    out.mkdir()
    bundled.build("astronaut", out, size=TRUTH_SIZE, seconds=TRUTH_SECONDS, seed=0, progress=False)
    return out
