"""The dense face mesh (MediaPipe's 478-point model in ONNX Runtime) against dlib's 68 points on a
photograph, against a known rotation of it, on a frame with no face, and with its model file altered."""

from __future__ import annotations


import cv2
import numpy as np
import pytest
from skimage import data

from lmgs_eval.data.ingest import mesh

# mesh vertex -> dlib-68 index: outer eye corners, mouth corners, chin
ANCHORS = [(33, 36), (263, 45), (61, 48), (291, 54), (152, 8)]


@pytest.fixture(scope="module")
def photo():
    import dlib

    from lmgs_eval.metrics.landmarks import dlib_model_path

    img = data.astronaut()  # a photograph of a real face, shipped by scikit-image
    box = mesh.dlib_box(img)
    shape = dlib.shape_predictor(str(dlib_model_path()))(img, dlib.rectangle(*[int(round(v)) for v in box]))
    d68 = np.array([[p.x, p.y] for p in shape.parts()], float)
    return img, d68, float(np.linalg.norm(d68[45] - d68[36]))


@pytest.fixture(scope="module")
def face_mesh():
    return mesh.FaceMesh()


def test_the_mesh_agrees_with_dlib_on_a_photograph(photo, face_mesh):
    img, d68, iod = photo
    pts, presence, detected = face_mesh.track([img, img])
    assert pts.shape == (2, 478, 3) and detected.tolist() == [True, False] and presence.min() > 10
    for m, d in ANCHORS:  # measured: 1-3 % of the distance between the outer eye corners
        assert np.linalg.norm(pts[-1, m, :2] - d68[d]) < 0.05 * iod, (m, d)


def test_tracking_follows_a_known_rotation_with_one_detection(photo, face_mesh):
    """The photograph turned by 0..20 degrees about the face, a degree a frame: the crop follows the eye line,
    so the mesh of frame k is frame 0's mesh turned by the same rotation, and the face is detected once."""
    img, d68, iod = photo
    cx, cy = d68.mean(0)
    turns = [cv2.getRotationMatrix2D((float(cx), float(cy)), float(k), 1.0) for k in range(21)]
    frames = [cv2.warpAffine(img, t, img.shape[1::-1], borderMode=cv2.BORDER_REFLECT) for t in turns]
    pts, presence, detected = face_mesh.track(frames)
    assert detected.sum() == 1 and presence.min() > 10
    ref = pts[0, :, :2]
    for k, t in enumerate(turns):  # measured: a median of 0.8-1.0 % of the eye distance
        err = np.median(np.linalg.norm(pts[k, :, :2] - (ref @ t[:, :2].T + t[:, 2]), axis=1))
        assert err < 0.03 * iod, (k, err / iod)


def test_a_frame_without_a_face_is_nan_and_detected_again(face_mesh, photo):
    img = photo[0]
    blank = np.full_like(img, 128)
    pts, presence, detected = face_mesh.track([blank, img, blank, img])
    assert np.isnan(pts[0]).all() and np.isnan(pts[2]).all() and np.isfinite(pts[[1, 3]]).all()
    assert presence[0] == -np.inf and presence[1] > 10
    assert detected.tolist() == [True, True, True, True]  # the frame after a lost face is detected afresh


def test_the_detector_finds_the_face_on_a_decoders_padded_frame_at_its_first_call():
    """A video decoder hands frames out as views whose rows are padded (not C-contiguous). dlib's
    detector, given such a view as its first image in a process, found no face where every later call
    finds one, so the mesh's first frame (and the track seeded from it) changed from run to run: the
    box must be the contiguous image's, on the first call of a fresh process."""
    import subprocess
    import sys

    code = ("import numpy as np; from skimage import data; from lmgs_eval.data.ingest.mesh import dlib_box\n"
            "img = data.astronaut(); wide = np.zeros((img.shape[0], img.shape[1] + 40, 3), np.uint8)\n"
            "wide[:, :img.shape[1]] = img; view = wide[:, :img.shape[1]]\n"
            "assert not view.flags['C_CONTIGUOUS']\n"
            "print(dlib_box(view)); print(dlib_box(np.ascontiguousarray(img)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split("\n")
    assert out[0] != "None" and out[0] == out[1], out
