"""Every model the ingest ships is read through a loader that checks the file: a missing or
altered copy (one byte flipped) stops with one line naming the file and which model it is."""

from __future__ import annotations

import shutil

import pytest

from lmgs_eval.data.ingest import blink, focal, mesh, segment, vendored
from lmgs_eval.errors import UserError

LOADERS = {
    "face_landmarks_detector.onnx": mesh.load_session,
    "face_blendshapes.tflite": blink.Blendshapes,
    "selfie_segmentation.tflite": segment.PersonSegmenter,
    "canonical_face_model.obj": focal.canonical_face,
}


def test_every_shipped_model_has_a_checking_loader():
    assert set(LOADERS) == set(vendored.MODELS)


@pytest.mark.parametrize("name", sorted(LOADERS))
def test_a_missing_or_altered_model_stops_with_one_line_naming_it(name, tmp_path):
    what = vendored.MODELS[name][0]
    gone = tmp_path / f"gone-{name}"
    with pytest.raises(UserError, match="missing") as e:
        LOADERS[name](gone)
    assert str(gone) in str(e.value) and what in str(e.value) and "\n" not in str(e.value)
    bad = tmp_path / name
    shutil.copyfile(vendored.FOLDER / name, bad)
    bad.chmod(0o644)
    raw = bytearray(bad.read_bytes())
    raw[len(raw) // 2] ^= 0x01
    bad.write_bytes(bytes(raw))
    with pytest.raises(UserError, match="altered") as e:
        LOADERS[name](bad)
    assert str(bad) in str(e.value) and what in str(e.value) and "\n" not in str(e.value)
    vendored.model(name)  # the shipped file is untouched and still passes its check
