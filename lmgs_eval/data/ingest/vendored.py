"""The model files the ingest ships (``models/``, each with its licence notice in ``models/README.md``),
checked before use: present and with the sha256 they were shipped with. Nothing is downloaded."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from lmgs.fileio import sha256_file
from lmgs_eval.errors import UserError

FOLDER = Path(__file__).with_name("models")
# file name -> (what it is, sha256)
MODELS = {
    "face_landmarks_detector.onnx": ("the face mesh model", "017f267ddd81e042224c43f00a3ef6d548a6595fe2a8e2a2ceacd0214269a79c"),
    "canonical_face_model.obj": ("the canonical face model", "8bac80443397e113f41a8b565ea72c59390bc031d9defab289dba7bc0c54e618"),
    "face_blendshapes.tflite": ("the face blendshape model", "4f36dded049db18d76048567439b2a7f58f1daabc00d78bfe8f3ad396a2d2082"),
    "selfie_segmentation.tflite": ("the person segmentation model", "8d13b7fae74af625c641226813616a2117bd6bca19eb3b75574621fc08557f27"),
}


def checked(path: str | Path, sha256: str, what: str) -> Path:
    """``path`` if it holds the file shipped (``sha256``); else a :class:`UserError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: {what} is missing (reinstall lmgs-eval)")
    got = sha256_file(path)
    if got != sha256:
        raise UserError(f"{path}: {what} is altered (sha256 {got[:12]}..., expected {sha256[:12]}...)")
    return path


def model(name: str, path: str | Path | None = None) -> Path:
    """The shipped model file ``name`` (a key of :data:`MODELS`), checked; with ``path``, that file checked
    against the shipped one's sha256 instead."""
    what, sha = MODELS[name]
    return checked(FOLDER / name if path is None else path, sha, what)


def check_all() -> None:
    """Every shipped model present and unaltered: run before an ingest writes anything."""
    for name in MODELS:
        model(name)


def allocate_quietly(interpreter) -> None:
    """A LiteRT interpreter's ``allocate_tensors`` with standard error held back: the runtime announces
    its XNNPACK delegate there once per process, and the ingest's output is its own."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            interpreter.allocate_tensors()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
