"""Pieces of the ingest tested on their own, without a video: the pose template's layout and
the torso layer behind the head, the depth / normal priors, the person mask's holes and its
growth against the plate."""

from __future__ import annotations

import numpy as np
import pytest

SIZE = 256


def test_template_is_the_frontal_layout_when_the_head_looks_aside(tmp_path):
    """The pose template's layout comes from the frames nearest frontal: a head that turns from 0 to
    30 deg and back (the generator's own 3D landmarks, projected) gives the frontal layout within
    1.3 % of the jaw width; the median over every frame (a 20-deg face) was 4.7 % off."""
    from lmgs_eval.data.bundled.generator import head_model
    from lmgs_eval.data.ingest import pose

    head = head_model("astronaut", SIZE)
    pts = head._rest_face[:68] - head._rest_face[:68].mean(0)
    f = 2.5 * SIZE

    def project(yaw_deg):
        out = []
        for y in np.radians(yaw_deg):
            rot = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
            p = pts @ rot.T
            z = head.D - p[:, 2]
            out.append(np.stack([f * p[:, 0] / z + SIZE / 2, -f * p[:, 1] / z + SIZE / 2], 1))
        return np.stack(out)

    front = project([0.0])[0]
    n = 75
    lms = project(30 * np.sin(np.pi * (np.arange(n) + 0.5) / n))
    assert abs(pose.yaw_asymmetry(front[None])[0]) < 0.05 and pose.yaw_asymmetry(lms).max() > 0.5
    tmpl = pose.build_template(lms)
    xy = pose._similarity(tmpl[:, :2] * [1, -1], front)
    assert np.linalg.norm(xy - front, axis=1).mean() < 0.025 * np.linalg.norm(front[16] - front[0])


def test_poses_are_smoothed_within_runs_not_across_a_left_out_gap():
    """Two runs of frames (a faceless stretch left out between them), the head still at 0 deg
    yaw in the first and at 20 deg in the second: smoothed run by run each keeps its own pose
    up to the seam; smoothed as one clip the frames by the seam blend the two."""
    from lmgs_eval.data.bundled.generator import head_model
    from lmgs_eval.data.ingest import pose

    head = head_model("astronaut", SIZE)
    pts = head._rest_face[:68] - head._rest_face[:68].mean(0)
    f = 2.5 * SIZE

    def project(y):
        rot = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
        p = pts @ rot.T
        z = head.D - p[:, 2]
        return np.stack([f * p[:, 0] / z + SIZE / 2, -f * p[:, 1] / z + SIZE / 2], 1)

    lms = np.stack([project(0.0)] * 20 + [project(np.radians(20.0))] * 20)
    runs = [slice(0, 20), slice(20, 40)]
    apart = np.degrees(pose.fit_poses(lms, SIZE, SIZE, focal=f, sigma=2.0, runs=runs).euler[:, 1])
    joined = np.degrees(pose.fit_poses(lms, SIZE, SIZE, focal=f, sigma=2.0).euler[:, 1])
    raw = np.degrees(pose.fit_poses(lms, SIZE, SIZE, focal=f, sigma=0).euler[:, 1])
    step = apart[20] - apart[19]
    assert abs(step - (raw[20] - raw[19])) < 0.1 and abs(step) > 15  # the whole turn at the seam
    assert np.ptp(apart[:20]) < 0.1 and np.ptp(apart[20:]) < 0.1
    assert abs(joined[20] - joined[19]) < 0.5 * abs(step)  # one clip: the seam is smeared


def test_torso_layer_continues_the_neck_up_behind_the_head():
    """``torso_imgs``: the frame's own neck and torso as filmed, and behind the head the neck's
    colour continued straight up, darker as it goes (by hand: 0.98 per pixel at 512 px)."""
    from lmgs_eval.data.ingest.parsing import NECK_PUSH, NECK_UP, Parts, torso_layer

    size = 512
    img = np.zeros((size, size, 3), np.uint8)
    head = np.zeros((size, size), bool)
    neck = np.zeros_like(head)
    torso = np.zeros_like(head)
    head[100:300, 150:350] = True
    neck[300:400, 200:300] = True
    torso[400:, :] = True
    img[neck] = (200, 150, 100)
    img[torso] = (10, 20, 30)
    rgb, alpha = torso_layer(img, Parts(head, neck, torso))
    assert np.array_equal(rgb[neck | torso], img[neck | torso]) and alpha[neck | torso].all()
    up = alpha & head
    cols = np.nonzero(up.any(0))[0]
    assert cols.min() == 200 and cols.max() == 299  # the neck's columns only
    # the neck is grown 3 px up, its colour taken NECK_PUSH px below that top and carried NECK_UP + NECK_PUSH + 1 px up
    top = 300 - 3 + NECK_PUSH - (NECK_UP + NECK_PUSH)
    assert not up[: top, 250].any() and up[top:300, 250].all()
    rows = np.arange(299, 280, -1)  # above the neck, upwards
    want = 200 * 0.98 ** (300 - 3 + NECK_PUSH - rows)  # darker by the pixels from the source row
    np.testing.assert_allclose(rgb[rows, 250, 0], want, atol=1.0)  # blurred along the column: a linear ramp keeps its values
    assert not alpha[head & ~up].any() and not alpha[~head & ~neck & ~torso].any()


def test_a_head_touching_the_top_edge_leaves_the_background_beside_it_background():
    """The person is one blob with its holes filled; but background cut off from the first corner
    by a head that reaches the top edge is not a hole (it reaches the edge elsewhere)."""
    from lmgs_eval.data.ingest.parsing import one_blob

    m = np.zeros((100, 100), bool)
    m[0:60, 40:60] = True  # a head touching the top edge
    m[60:, 20:80] = True  # the shoulders, down to the bottom edge
    m[70:80, 45:55] = False  # a hole inside the person
    m[5:8, 5:8] = True  # a speck apart from the person
    got = one_blob(m)
    want = m.copy()
    want[70:80, 45:55] = True
    want[5:8, 5:8] = False
    assert np.array_equal(got, want)  # the background right of the head (cut off from (0, 0)) stays background


def test_the_person_grows_against_the_plate_into_the_edge_grabcut_missed():
    """A person whose soft edge GrabCut's reduced copy missed: the mask grows back to where the
    frame differs from the plate, and no further into a noisy background."""
    import cv2

    from lmgs_eval.data.ingest.parsing import GROW_REACH, refine_person

    rng = np.random.default_rng(0)
    size = 200
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    r = np.hypot(yy - 130, xx - 100)
    alpha = np.clip(61.0 - r, 0, 1)  # a disc of radius 60 px, its edge one pixel soft
    plate = np.stack([70 + 0.3 * xx, 90 + 0.2 * yy, np.full_like(xx, 120.0)], -1)
    frame = plate * (1 - alpha[..., None]) + np.array([200.0, 150, 110]) * alpha[..., None]
    frame = np.clip(np.rint(frame + rng.normal(0, 2.0, frame.shape)), 0, 255).astype(np.uint8)
    plate = np.rint(plate).astype(np.uint8)
    truth = alpha >= 0.5
    short = r < 56  # GrabCut's outline four pixels inside
    got = refine_person(short, frame, plate)
    assert (truth & ~got).sum() == 0  # every pixel of the person found
    # beyond the half-covered edge, only pixels the person's colour mixes into (its soft rim) join
    assert (got & ~truth).any() and not (got & (alpha == 0)).any()
    # a plate wrong in a wide ring round the person (a shadow, say) lets it grow GROW_REACH of the side, no more
    wrong = plate.copy()
    wrong[(r > 50) & (r < 90)] = 0
    far = refine_person(short, frame, wrong)
    reach = round(GROW_REACH * size)
    assert np.array_equal(far, cv2.dilate(short.astype(np.uint8), np.ones((2 * reach + 1,) * 2, np.uint8)) > 0)
    # a plate that matches nowhere (a moving camera) sets the noise level so high that nothing grows
    assert np.array_equal(refine_person(short, frame, np.zeros_like(plate)), short)


def test_depth_prior_is_the_ellipsoid_and_beyond_it_the_sheet_through_its_outline():
    """A sphere of radius 0.1 m, 1 m in front of the camera (world = camera, OpenCV axes), seen at
    focal 100 on a 41 px frame: a ray that meets it takes the nearer intersection, one that misses
    takes its point nearest the centre, facing the camera; ``rim=False`` leaves it empty."""
    from lmgs_eval.data.geometry import render_prior

    f, w, r, dist = 100.0, 41, 0.1, 1.0
    mask = np.ones((w, w), bool)
    depth, normal = render_prior(np.eye(4), f, w, w, np.array([0.0, 0.0, dist]), np.full(3, r), mask)
    bare, _ = render_prior(np.eye(4), f, w, w, np.array([0.0, 0.0, dist]), np.full(3, r), mask, rim=False)
    seen = 0
    for y in range(w):
        for x in range(w):
            d = np.array([(x + 0.5 - w / 2) / f, (y + 0.5 - w / 2) / f, 1.0])  # the ray, z = 1
            c = np.array([0.0, 0.0, dist])
            t_near = (d @ c) / (d @ d)  # the ray's point nearest the centre (its camera z)
            miss2 = (c - t_near * d) @ (c - t_near * d) - r * r  # squared distance beyond the sphere
            if miss2 < 0:  # a hit: the nearer root of |t d - c| = r
                t = t_near - np.sqrt(-miss2 / (d @ d))
                n = (t * d - c) / r
                assert bare[y, x] == depth[y, x]
                seen += 1
            else:
                t, n = t_near, -d / np.linalg.norm(d)
                assert bare[y, x] == 0
            assert depth[y, x] == pytest.approx(t, rel=1e-4), (y, x)  # float32; the depth PNG holds 0.1 mm
            np.testing.assert_allclose(normal[y, x], n, atol=1e-3)
    assert 0 < seen < w * w  # both kinds of pixel were in the frame
    # the sheet meets the sphere at its outline without a step: along the row through the centre,
    # from the outermost hit to the first sheet pixel the depth moves less than between the two
    # outermost hits (the sphere's own steepness there)
    row, hits = depth[w // 2], bare[w // 2] > 0
    last = int(np.nonzero(hits)[0].max())
    assert abs(row[last + 1] - row[last]) < abs(row[last] - row[last - 1])


def _sphere_mesh(r: float, centre, rows: int = 48, cols: int = 96):
    """A latitude-longitude triangulation of a sphere: vertices ``[V, 3]``, triangles ``[F, 3]``."""
    th = np.linspace(0, np.pi, rows + 1)[:, None]
    ph = np.linspace(0, 2 * np.pi, cols, endpoint=False)[None, :]
    v = np.stack([np.sin(th) * np.cos(ph), np.cos(th) + 0 * ph, np.sin(th) * np.sin(ph)], -1).reshape(-1, 3) * r + np.asarray(centre)
    a = np.arange(rows)[:, None] * cols + np.arange(cols)[None, :]
    b = np.arange(rows)[:, None] * cols + (np.arange(cols)[None, :] + 1) % cols
    tri = np.concatenate([np.stack([a, a + cols, b], -1).reshape(-1, 3), np.stack([b, a + cols, b + cols], -1).reshape(-1, 3)])
    return v, tri


def test_a_triangle_mesh_renders_as_the_surface_it_approximates():
    """A sphere of radius 0.1 m, 1 m away, triangulated (48 x 96) and rendered by
    :func:`render_mesh`, against the sphere itself ray-cast exactly (:func:`render_prior`; its
    own test above checks it by hand): the same pixels but at the outline, depth within the
    triangulation's sag, normals facing the camera whichever way the triangles wind; nearer
    triangles hide farther ones; a triangle behind the camera is left out."""
    from lmgs_eval.data.geometry import render_mesh, render_prior

    f, w, r, c = 300.0, 96, 0.1, np.array([0.02, -0.01, 1.0])
    v, tri = _sphere_mesh(r, c)
    exact, n_exact = render_prior(np.eye(4), f, w, w, c, np.full(3, r), np.ones((w, w), bool), rim=False)
    for faces in (tri, tri[:, ::-1]):  # both windings
        depth, normal = render_mesh(v, faces, f, w, w)
        both = (depth > 0) & (exact > 0)
        assert both.sum() >= 0.97 * (exact > 0).sum() and both.sum() >= 0.95 * (depth > 0).sum()
        inner = both & (n_exact[..., 2] < -0.6)  # away from the outline, where the facets' sag is small
        # the most a facet lies inside the sphere, along its normal: its circumradius (half a
        # latitude step's diagonal) squared over the diameter; along a ray at most twice that here
        sag = r * (np.pi / 48) ** 2 / 4
        assert np.abs(depth[inner] - exact[inner]).max() <= 2 * sag
        angle = np.degrees(np.arccos(np.clip((normal[inner] * n_exact[inner]).sum(-1), -1, 1)))
        assert angle.mean() < 1.5 and angle.max() < 5.0
        assert (normal[depth > 0][:, 2] < 0).mean() > 0.99  # facing the camera (OpenCV: -z)
    # a square between the camera and the sphere hides it, whichever is listed first; a square with
    # corners behind the camera is not drawn
    sq = np.array([[-0.02, -0.02, 0.85], [0.02, -0.02, 0.85], [0.02, 0.02, 0.85], [-0.02, 0.02, 0.85]])
    two = np.array([[0, 1, 2], [0, 2, 3]])
    depth, _ = render_mesh(np.concatenate([v, sq]), np.concatenate([tri, len(v) + two]), f, w, w)
    first, _ = render_mesh(np.concatenate([sq, v]), np.concatenate([two, 4 + tri]), f, w, w)
    assert depth[w // 2, w // 2] == pytest.approx(0.85, rel=1e-6) and np.array_equal(depth, first)
    assert (depth == np.float32(0.85)).sum() == pytest.approx((0.04 * f / 0.85) ** 2, rel=0.1)
    behind = sq * np.array([1.0, 1.0, -1.0]) + np.array([0.0, 0.0, 0.8])  # z = -0.05 at two corners
    behind[:2, 2] = 0.9
    depth, _ = render_mesh(np.concatenate([v, behind]), np.concatenate([tri, len(v) + two]), f, w, w)
    np.testing.assert_array_equal(depth, render_mesh(v, tri, f, w, w)[0])


def test_the_tracked_mesh_is_lifted_onto_its_rays_at_the_posed_templates_depth():
    """:func:`pose.lift_mesh` on a synthetic track: the canonical face posed 0.9 m from a camera
    (focal 600, 256 px), seen in pixels with z in the same pixels (as the tracker gives it:
    relative to the face, scaled like x and y), and a template (68 points) posed with it. The
    lifted vertices project back onto the tracked pixels, their depth relief is the face's (the
    tracker's z times depth over focal length), and the template's inner points meet them."""
    from lmgs_eval.data.ingest.focal import canonical_face
    from lmgs_eval.data.ingest.lips import MESH_TO_68
    from lmgs_eval.data.ingest.pose import lift_mesh

    f, w = 600.0, 256
    face = canonical_face()  # metres, OpenCV axes
    cam = face + np.array([0.01, -0.02, 0.9])  # camera coordinates: the face 0.9 m away
    uv = f * cam[:, :2] / cam[:, 2:] + w / 2
    template = cam[list(MESH_TO_68)]  # world = camera
    # the tracker's relative z: its zero is its own, its pixels those of x and y at the head's depth
    z_px = (cam[:, 2] - cam[:, 2].mean()) * f / np.median(template[:, 2])
    mesh = np.concatenate([np.concatenate([uv, z_px[:, None]], 1), np.full((10, 3), 5.0)])[None]  # + 10 iris points
    got = lift_mesh(template, np.eye(4)[None], f, mesh, w, w)[0]
    assert got.shape == (468, 3)
    np.testing.assert_allclose(f * got[:, :2] / got[:, 2:] + w / 2, uv, atol=1e-6)
    np.testing.assert_allclose(got, cam, atol=1e-9)
    # a template 1 cm behind the face places the face 1 cm back: the inner points decide, not the mean
    back = lift_mesh(template + np.array([0.0, 0.0, 0.01]), np.eye(4)[None], f, mesh, w, w)[0]
    np.testing.assert_allclose(back[:, 2] - cam[:, 2], 0.01, atol=1e-3)  # within a mm: the relief scales with the depth
    assert np.all(np.isnan(lift_mesh(template, np.eye(4)[None], f, np.full((1, 478, 3), np.nan), w, w)))


def test_the_head_ellipsoid_is_moved_to_meet_the_face_meshs_outline():
    """:func:`meet_mesh`: the "face" a cap of a sphere 1 m from the camera, the "head" the same
    sphere 3 cm further back, in a world whose +z faces the camera (as the ingest's template's):
    the head is moved the 3 cm forward, within the sphere's own slope across the few pixels between
    the mesh's edge and the ring beside it."""
    from lmgs_eval.data.geometry import meet_mesh

    f, w, r = 1200.0, 192, 0.1
    w2c = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1.0], [0, 0, 0, 1]])  # world origin 1 m ahead, +z to the camera
    v, tri = _sphere_mesh(r, np.array([0.0, 0.0, 1.0]))  # camera coordinates
    cap = tri[(v[tri][:, :, 2] < 0.91).all(1)]  # facing the camera, where the sphere is not yet steep
    centre, step = meet_mesh(np.array([0.0, 0.0, -0.03]), np.full(3, r), w2c[None], v[None], cap, f, w, w)
    assert step == pytest.approx(0.03, abs=0.002)
    np.testing.assert_allclose(centre, [0.0, 0.0, -0.03 + step])
    same, none = meet_mesh(np.zeros(3), np.full(3, r), w2c[None], np.full((1, len(v), 3), np.nan), tri, f, w, w)
    assert none == 0.0 and np.array_equal(same, np.zeros(3))


def _die(a, b):  # a chunk whose worker process ends without a Python error, as one killed for memory
    import os

    os._exit(1)


def test_a_worker_that_dies_is_one_clear_error_not_a_broken_pool():
    from lmgs_eval.data.ingest.frames import CHUNK, run_chunks
    from lmgs_eval.errors import UserError

    with pytest.raises(UserError, match=r"_die: a worker process of the 2 stopped abruptly .* --jobs 1"):
        run_chunks(_die, 2 * CHUNK, ((), ()), jobs=2)
    assert run_chunks(lambda a, b: (a, b), 2 * CHUNK, ((), ()), jobs=1) == [(0, CHUNK), (CHUNK, 2 * CHUNK)]
