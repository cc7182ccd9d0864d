"""``lmgs-eval ingest`` outside a near-frontal head before a still camera: the generator's
``turn`` and ``zoom`` motion variants, ingested, against their truth."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import run_cli

SIZE = 256

# A head that turns (yaw +-28 deg, pitch +-10 deg over the clip) and a camera that zooms
# (focal +-8 %), both of the generator's motion option; 2 s keep each build and ingest short.
MOTION_SECONDS = 2.0


def _motion_subject(tmp_path_factory, kind: str) -> tuple[Path, Path, str]:
    from lmgs_eval.data import bundled

    truth = tmp_path_factory.mktemp(f"truth-{kind}") / "astronaut"
    truth.mkdir()
    bundled.build("astronaut", truth, size=SIZE, seconds=MOTION_SECONDS, seed=0, progress=False, motion=kind)
    root = tmp_path_factory.mktemp(f"data-{kind}")
    rc, out, err = run_cli("ingest", str(truth / "astronaut.mp4"), "--name", kind, "--size", str(SIZE),
                           "--data-root", str(root), "--quiet")
    assert rc == 0, err
    return truth, root / kind, out + err


@pytest.fixture(scope="module")
def turning(tmp_path_factory) -> tuple[Path, Path, str]:
    return _motion_subject(tmp_path_factory, "turn")


@pytest.fixture(scope="module")
def zooming(tmp_path_factory) -> tuple[Path, Path, str]:
    return _motion_subject(tmp_path_factory, "zoom")



def test_turning_head_against_the_truth(turning):
    from lmgs_eval.data.ingest.compare import compare

    truth, folder, _ = turning
    got = compare(truth, folder)
    # measured (this fixture): rotation 2.50 deg against the truth's own 19.35 deg spread with the
    # poses from the dense mesh, 15 of the 50 frames refined by the tracked texture and the other 35
    # carrying their correction (3.88 with every frame left unrefined; 5.83 from the 68-point
    # template on dlib's points, whose nose and mouth points follow 60-70 % of the surface points'
    # motion on this head); landmarks 2.54 px,
    # 1.82 without the jaw contour (silhouette against surface points), mouth 2.43; distance
    # 1.71 % (1.49 unrefined); head IoU 0.844 (the truth's hair beside the jaw is a still layer it labels torso, the
    # ingest labels it head); focal 0.78 of the truth (1.94 widths; this generated head's shape
    # pulls the fit short, see design.md)
    assert got["rotation_spread_deg"] > 15.0  # the head does turn
    assert got["rotation_deg"] < 3.2
    assert got["rotation_deg"] < 0.5 * got["rotation_spread_deg"]
    assert got["inner_landmark_px"] < 2.5 and got["landmark_px"] < 3.5 and got["mouth_landmark_px"] < 3.2
    assert got["translation_rel"] < 0.03
    assert got["head_iou"] > 0.82
    man = json.loads((folder / "manifest.json").read_text())
    assert set(man["flags"]) == {"short_clip", "small_face"}  # a turn is not a zoom
    # turned up to 28 deg, too few frames look like the reference for the tracked texture to
    # refine them all: the others carry their refined neighbours' correction
    tex = man["pose"]["texture_refinement"]
    assert 0 < tex["refined"] < man["frames"]["kept"] and tex["refined"] + tex["carried"] == man["frames"]["kept"]
    assert any(n.startswith(f"pose: {tex['refined']} of {man['frames']['kept']} frames refined") and f"the other {tex['carried']}" in n
               for n in man["notes"]), man["notes"]
    assert man["pose"]["source"].startswith("the subject's shape")
    assert man["pose"]["pitch_yaw_roll_deg_max"][1] - man["pose"]["pitch_yaw_roll_deg_min"][1] > 30.0


def test_zooming_camera_is_flagged_and_read_as_distance(zooming):
    """A zoom of +-8 % cannot be written into the layout (one focal length); the ingest flags it
    (the frame outside the head scales with the face) and the fit reads it as the camera's
    distance."""
    from lmgs_eval.data.ingest.compare import compare

    truth, folder, text = zooming
    man = json.loads((folder / "manifest.json").read_text())
    assert "zoom" in man["flags"] and "zooms" in man["flags"]["zoom"]
    assert any(l.startswith("warning:") and "zooms" in l for l in text.splitlines())  # said in one line
    sc = man["pose"]["scale"]
    # measured: the frame scales by 15.8 %, the face by 15.1 % (slope 1.05, r 0.999); the truth's focal by 16 %
    assert 0.12 < sc["frame_scale_range"] < 0.2 and 0.8 < sc["slope"] < 1.3 and sc["corr"] > 0.95
    got = compare(truth, folder)
    assert got["focal_range_true"] == pytest.approx(0.16, abs=0.005)
    # the whole zoom went into the camera's distance (measured slope -0.98, mean error 5.1 %)
    assert got["distance_zoom_slope"] < -0.8 and got["translation_rel"] > 0.03
    # the head itself is fitted as well as before a still camera (measured: rotation 0.36 deg,
    # landmarks 1.11 px, head IoU 0.890; 0.915 with the head label at the head outline, as above)
    assert got["rotation_deg"] < 0.8 and got["landmark_px"] < 1.5 and got["head_iou"] > 0.88
