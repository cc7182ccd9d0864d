"""The stages of :func:`lmgs_eval.data.ingest.pipeline.ingest`, each writing into the work folder."""

from __future__ import annotations

import json
import time

import numpy as np

from lmgs_eval.data.audio import write_wav
from lmgs_eval.data.images import read_rgb_u8, write_rgb
from lmgs_eval.data.ingest import decode, pose as pose_mod, track as track_mod, writer, zoom as zoom_mod
from lmgs_eval.data.ingest import frames as frames_mod
from lmgs_eval.data.ingest.align import MIN_FOLLOW, MIN_SHARE
from lmgs_eval.data.ingest.checks import INGEST_VERSION, MIN_FACE_PX, MOVING_SHARE, STATIC_LEVELS, check_frames
from lmgs_eval.data.ingest.crop import choose_window
from lmgs_eval.data.ingest.parsing import PlateBuilder
from lmgs_eval.data.layout_writer import file_hashes, write_au_csv, write_json, write_lms, write_track_params, write_transforms
from lmgs_eval.data.video import write_video
from lmgs_eval.errors import UserError

SPF = 640
MEET_FRAMES = 20  # frames the head ellipsoid is fitted to the face mesh's outline on


def track(ctx, info: decode.VideoInfo) -> None:
    """Decode at 25 fps, track the face, look for scene cuts."""
    import cv2

    from lmgs_eval.data.ingest.mesh import FaceMesh

    t0 = time.perf_counter()
    thumbs = np.zeros((info.n_frames, 64, 64), np.float32)
    face_mesh = FaceMesh()
    mesh = np.full((info.n_frames, 478, 3), np.nan, np.float32)

    def frames():
        for k, img in decode.frames_25fps(info):
            thumbs[k] = cv2.resize(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), (64, 64), interpolation=cv2.INTER_AREA) / 255.0
            mesh[k] = face_mesh.step(img)[0]
            yield k, img

    bar = ctx.bar(info.n_frames, "decode + track")
    tr = track_mod.track_faces(frames(), info.n_frames, bar)
    if bar is not None:
        bar.close()
    ctx.timed("decode_track", t0, info.n_frames)
    jumps = decode.scene_cuts(thumbs)
    light = decode.light_jumps(thumbs, jumps)
    cuts = [k for k in jumps if k not in light]
    if cuts:
        raise UserError(f"{ctx.video}: {len(cuts)} scene cut(s) at frame {_when(cuts)}; ingest one shot at a time "
                        f"(cut the video there, e.g. ffmpeg -ss/-to)")
    if light:
        raise UserError(f"{ctx.video}: the light changes at once at frame {_when(light)} (the same picture, brighter or darker); "
                        f"the plate and the colours assume one lighting: ingest the parts apart (cut the video there, e.g. ffmpeg -ss/-to)")
    many = tr.faces.max(initial=0)
    other = np.nonzero(tr.others > 0)[0]
    if many > 1 or len(other):
        seen = [f"up to {many} faces in one frame"] if many > 1 else []
        if len(other):
            seen.append(f"a face other than the tracked one in frames {_ranges(other.tolist())}, left alone")
        ctx.warn("several_faces", f"{ctx.video}: {'; '.join(seen)}; tracked the largest, most central face and kept to it")
    writer.save_npz(ctx.work / "track.npz", lms=tr.lms, faces=tr.faces, detected=tr.detected, others=tr.others, mesh=mesh)


def frames(ctx, info: decode.VideoInfo, tr, audio: np.ndarray) -> None:
    """Checks (coverage, size, audio length), the crop window, the frames and their landmarks."""
    t0 = time.perf_counter()
    lms, cov = track_mod.fill_gaps(tr["lms"], str(ctx.video))
    first, last = check_frames(ctx, info, len(audio) // SPF, cov.first, cov.last, cov.dropped)
    source = cov.kept[cov.kept < last]  # the source frame of each subject frame
    lms = lms[: len(source)]
    if cov.cut:
        ctx.warn("faceless_ends", f"{len(cov.cut)} frames without a face at the start/end were cut (frames {_ranges(cov.cut)})")
    gone = [k for k in cov.dropped if k < last]
    if gone:
        ctx.warn("faceless_gaps", f"{len(gone)} frames without a face for more than {track_mod.MAX_GAP} in a row were left out "
                 f"(frames {_ranges(gone)}; {len(gone) / 25:.1f} s): the subject's frames and audio jump over them, as at a cut")
    missing = [k for k in cov.missing if k < last]
    if missing:
        ctx.warn("interpolated", f"{len(missing)} frames without a detected face were interpolated from their neighbours (frames {_ranges(missing)})")
    jaw = float(np.median(np.linalg.norm(lms[:, 16] - lms[:, 0], axis=1)))
    if jaw < MIN_FACE_PX:
        ctx.warn("small_face", f"{ctx.video}: the face is small ({jaw:.0f} px between the jaw corners; at least {MIN_FACE_PX} px advised): landmarks and frames will be coarse")
    win, notes = choose_window(lms, info.width, info.height, ctx.cfg.size, ctx.cfg.crop)
    ctx.log += notes
    n = len(source)
    at = {int(k): i for i, k in enumerate(source)}
    out = ctx.sub / "ori_imgs"
    out.mkdir(exist_ok=True)
    bar = ctx.bar(n, "crop + frames")
    for k, img in decode.frames_25fps(info):
        if k >= last:
            break
        if k in at:
            write_rgb(out / f"{at[k]}.jpg", win.apply(img))
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    lms_out = win.to_out(lms)
    smooth = lms_out.copy()
    if ctx.cfg.smooth_window > 1:  # each run of consecutive frames alone: no smoothing across a left-out gap
        for seg in track_mod.segments(source):
            smooth[seg] = track_mod.smooth_landmarks(lms_out[seg], ctx.cfg.smooth_window)
    for i in range(n):
        write_lms(out / f"{i}.lms", smooth[i])
    found = ~np.isin(source, missing)
    mesh = tr["mesh"][source].astype(np.float64)  # the dense mesh in output pixels (z in the same scale)
    mesh[..., :2] = win.to_out(mesh[..., :2])
    mesh[..., 2] *= win.scale
    writer.save_npz(ctx.work / "frames.npz", lms=smooth, raw=lms_out, found=found, first=first, last=last, source=source,
             window=json.dumps(win.to_json()), jaw_px=jaw, mesh=mesh.astype(np.float32))
    ctx.timed("crop_frames", t0, n)


def source_frames(sel) -> np.ndarray:
    """The source video's frame number of each subject frame (``frames.npz``)."""
    return sel["source"] if "source" in sel.files else np.arange(int(sel["first"]), int(sel["last"]))


def _when(ks: list[int]) -> str:
    """The first five source frames of ``ks`` with their times, for a one-line error."""
    return ", ".join(f"{k} ({k / 25:.2f} s)" for k in ks[:5])


def _ranges(ks) -> str:
    ks = sorted(ks)
    parts, a = [], ks[0]
    for p, q in zip(ks, ks[1:] + [None]):
        if q != p + 1:
            parts.append(f"{a}-{p}" if p > a else f"{a}")
            a = q
    return ", ".join(parts[:6]) + (", ..." if len(parts) > 6 else "")


POSE_SOURCES = {
    "mesh": "the subject's shape (canonical face's skull vertices, fitted to the dense mesh) posed per frame by perspective-n-point",
    "landmarks": "the 68-point template (the subject's frontal layout, generic relief) posed per frame on dlib's landmarks",
}


def pose(ctx, sel) -> None:
    t0 = time.perf_counter()
    lms = sel["lms"]
    s = ctx.cfg.size
    frames = [ctx.sub / "ori_imgs" / f"{i}.jpg" for i in range(len(lms))] if ctx.cfg.pose_refine else None
    src = source_frames(sel)
    focal, ff = ctx.cfg.focal, None
    if focal is None:
        from lmgs_eval.data.ingest.focal import fit_focal

        ff = fit_focal(sel["mesh"], s, s, mapper=ctx.workers.executor().map if ctx.workers is not None else None)
        focal = ff.focal
        rng = f"{ff.lo / s:.2f}-{ff.hi / s:.2f}"
        ctx.log.append(f"focal length {ff.focal / s:.2f} frame widths (interval {rng}) from the dense mesh of {ff.frames} frames; "
                       + ("the clip's head motion decides little of it (evidence "
                          f"{ff.evidence:.2f} < 1): the prior about the field's 2.5 widths does; pass --focal if the camera's is known"
                          if ff.evidence < 1 else f"the clip's evidence {ff.evidence:.2f}"))
    fit = pose_mod.fit_poses(lms, s, s, focal=focal, sigma=ctx.cfg.pose_sigma, frames=frames,
                             runs=track_mod.segments(src), mesh=sel["mesh"] if ctx.cfg.pose_from == "mesh" else None)
    ref = int(src[fit.reference])  # in the source's frame numbers
    kind = "dense-mesh" if fit.source == "mesh" else "landmark"
    tex = fit.texture
    if tex is not None and tex.used.any():
        ctx.log.append(f"pose: {int(tex.used.sum())} of {len(lms)} frames refined by the upper head's texture tracked "
                       f"from frame {ref}" + (f"; the other {tex.carried} keep their {kind} pose's motion, corrected as their "
                                              "refined neighbours were (turned too far from that frame, or too little texture "
                                              "followed)" if tex.carried else ""))
    elif tex is not None and tex.refused == "rough":
        ctx.log.append(f"pose: the {kind} poses are kept: the upper head's texture could refine {tex.refinable} of {len(lms)} "
                       f"frames, but its poses turn less smoothly than the {kind} poses (second differences "
                       f"{tex.roughness[1]:.2f} deg against {tex.roughness[0]:.2f}): it would add noise, not take it out")
    elif tex is not None and tex.refused == "flat":
        ctx.log.append(f"pose: the {kind} poses are kept: the upper head's texture could refine {tex.refinable} of {len(lms)} "
                       f"frames, but its poses turn {tex.follows:.2f} times as far as the {kind} poses (less than "
                       f"{MIN_FOLLOW:.2f}): the tracked texture reads the head's turn short (on real clips seen with glasses and a "
                       "fringe in the tracked region), which misplaces a turned head")
    elif tex is not None:
        ctx.log.append(f"pose: the {kind} poses are kept: the upper head's texture could refine {tex.refinable} of {len(lms)} "
                       f"frames, fewer than {100 * MIN_SHARE:.0f} % (the head turns too far from frame {ref}, or too little "
                       "texture follows)")
    write_transforms(ctx.sub, fit.c2w, fit.focal, s, s)
    write_track_params(ctx.sub / "track_params.pt", fit.euler, fit.trans, fit.focal)
    np.save(ctx.sub / "lms3d.npy", pose_mod.lift_landmarks(fit, lms, s, s))
    sc = zoom_mod.check_scale(ctx.sub / "ori_imgs", lms, fit.c2w, s)
    if sc.zooms:
        ctx.warn("zoom", f"{ctx.video}: the frame outside the head scales with the face ({100 * sc.frame_range:.1f} % and "
                 f"{100 * sc.face_range:.1f} % over the clip, slope {sc.slope:.2f}): the camera zooms or moves along its view. "
                 f"The one focal length of the layout reads it as the camera's distance (for the head's images nearly the "
                 f"same: a zoom and a dolly look alike on a face); the plate and the torso assume a still frame and are "
                 f"wrong where the frame is scaled")
    failed = int(np.isnan(sc.frame).sum())
    if failed > len(sc.frame) // 2:
        ctx.log.append(f"zoom check: {failed} of {len(sc.frame)} sampled frames could not be registered outside the head "
                       f"(too little of it, or too little texture): a zoom would go unseen; the face's scale changes by {100 * sc.face_range:.1f} %")
    writer.save_npz(ctx.work / "pose.npz", w2c=fit.w2c, c2w=fit.c2w, euler=fit.euler, trans=fit.trans, template=fit.template,
             focal=fit.focal, reproj=fit.reproj_px, focal_fit=json.dumps(ff.to_json(s) if ff is not None else {"method": "--focal"}),
             scale=json.dumps(sc.to_json()), source=fit.source,
             mesh_reproj=fit.mesh_reproj_px if fit.mesh_reproj_px is not None else np.full(len(lms), np.nan),
             texture=json.dumps({} if tex is None else
                                {"reference_frame": ref, "refinable": tex.refinable, "refined": int(tex.used.sum()),
                                 "carried": tex.carried, "roughness_deg": [round(x, 4) if np.isfinite(x) else None for x in tex.roughness],
                                 "follows": round(tex.follows, 4) if np.isfinite(tex.follows) else None}))
    ctx.timed("pose", t0, len(lms))


def parsing(ctx, sel) -> None:
    """Per-frame person masks (the selfie segmenter); the plate from their background pixels; then
    the parsing maps and mouth masks."""
    t0 = time.perf_counter()
    lms = sel["lms"]
    n, s = len(lms), ctx.cfg.size
    for d in ("parsing", "teeth_mask"):
        (ctx.sub / d).mkdir(exist_ok=True)
    plate = PlateBuilder(s, s, ctx.cfg.plate_frames, n)
    masks = ctx.work / "person"
    masks.mkdir(exist_ok=True)
    bar = ctx.bar(n, "parsing")
    for chunk in frames_mod.run_chunks(frames_mod.parse, n, ((ctx.sub, masks, lms), (frozenset(plate.keep),)), ctx.jobs, bar,
                                         workers=ctx.workers):
        for k, img, person in chunk:
            plate.add(k, img, person)
    if bar is not None:
        bar.close()
    bc, seen, resid = plate.plate()
    write_rgb(ctx.sub / "bc.jpg", bc)
    bar = ctx.bar(n, "parsing against the plate")
    frames_mod.run_chunks(frames_mod.refine, n, ((ctx.sub, masks, lms), ()), ctx.jobs, bar, workers=ctx.workers)
    if bar is not None:
        bar.close()
    ctx.log.append(f"plate: {100 * seen.mean():.1f} % of its pixels seen behind the person, the rest inpainted; the background "
                   f"differs from it by {np.median(resid):.1f} grey levels in the median frame ({max(resid):.1f} at most)")
    src = source_frames(sel)
    moving = [int(src[k]) for k, r in zip(plate.ids, resid) if r > STATIC_LEVELS]
    if len(moving) > MOVING_SHARE * len(resid) + 1:
        ctx.warn("moving_camera", f"{ctx.video}: the background differs from the plate by more than {STATIC_LEVELS:g} grey levels "
                 f"in {len(moving)} of {len(resid)} sampled frames (video frames {_ranges(moving)}): a moving camera or changing "
                 f"light; the plate assumes a static camera and is wrong there")
    ctx.timed("parsing", t0, n)


def geometry(ctx, sel) -> None:
    """Depth and normal priors inside each frame's head mask: the tracked face mesh where it
    covers the head, the posed head ellipsoid elsewhere."""
    from lmgs_eval.data.geometry import head_ellipsoid

    t0 = time.perf_counter()
    n, s = len(sel["lms"]), ctx.cfg.size
    pz = np.load(ctx.work / "pose.npz")
    centre, axes = head_ellipsoid(pz["template"])
    face = None
    if ctx.cfg.priors == "mesh" and "mesh" in sel.files:
        from lmgs_eval.data.geometry import meet_mesh
        from lmgs_eval.data.ingest.focal import canonical_triangles

        verts = pose_mod.lift_mesh(pz["template"], pz["w2c"], float(pz["focal"]), sel["mesh"], s, s).astype(np.float32)
        face = ctx.work / "face_mesh.npy"
        np.save(face, verts)
        pick = np.linspace(0, n - 1, min(n, MEET_FRAMES)).round().astype(int)
        centre, step = meet_mesh(centre, axes, pz["w2c"][pick], verts[pick], canonical_triangles(), float(pz["focal"]), s, s)
        ctx.log.append(f"depth priors: the tracked face mesh over the face, the head ellipsoid beyond it moved {100 * step:+.1f} cm "
                       "along the head's axis to meet the mesh's outline")
    for d in ("depth", "normal"):
        (ctx.sub / d).mkdir(exist_ok=True)
    bar = ctx.bar(n, "depth + normal priors")
    frames_mod.run_chunks(frames_mod.geometry, n, ((ctx.sub, pz["w2c"], float(pz["focal"]), centre, axes), (face,)), ctx.jobs, bar,
                          workers=ctx.workers)
    if bar is not None:
        bar.close()
    ctx.timed("geometry", t0, n)


def composites(ctx, sel) -> None:
    """``gt_imgs`` (the frame over the plate outside the person) and ``torso_imgs`` (RGBA)."""
    t0 = time.perf_counter()
    n = len(sel["lms"])
    for d in ("gt_imgs", "torso_imgs"):
        (ctx.sub / d).mkdir(exist_ok=True)
    bar = ctx.bar(n, "composites")
    frames_mod.run_chunks(frames_mod.composite, n, ((ctx.sub,), ()), ctx.jobs, bar, workers=ctx.workers)
    if bar is not None:
        bar.close()
    ctx.timed("composites", t0, n)


def speech_lips(ctx, aud: np.ndarray, key: dict) -> dict:
    """Whether the clip's mouth opening follows its speech (:func:`lmgs.lips_check.speech_coherence` on the written
    landmarks and audio), with the shipped lip model, or the one trained on generated speech alone where the shipped one
    was adapted on this very video; a note (or a flag, for an offset audio track) says what it means for the clip's LMD."""
    from lmgs.lips_check import speech_coherence
    from lmgs.lips_weights import DEFAULT, adapted_on

    t0 = time.perf_counter()
    seen = {c.get("sha256") for c in adapted_on(DEFAULT) or ()}
    weights = "lips_generated.pt" if key["input_sha256"] in seen else DEFAULT
    lms3d = np.load(ctx.sub / "lms3d.npy")
    coh = speech_coherence(aud, lms3d, weights)
    v = coh["verdict"]
    if v in ("follows", "not shown"):
        how = (f"r {coh['r']:.2f} at lag {coh['lag']:+d} within +-{coh['near_lag']} frames; chance {coh['chance_mean']:.2f} "
               f"+- {coh['chance_sd']:.2f}, from lags of {coh['far_lag']} frames and more; lip model {weights}")
        ctx.log.append(f"speech and lips: the mouth's opening follows the speech ({how})" if v == "follows" else
                       f"speech and lips: the mouth's opening follows the speech no better than chance ({how}): on this clip "
                       "LMD measures expression (smiles, a mouth open in pauses) as much as lip sync, unless the clip is too "
                       "short to show it")
    elif v == "offset":
        ctx.warn("av_offset", f"{ctx.video}: the mouth's opening follows the speech best {abs(coh['best_far_lag'])} frames "
                 f"({abs(coh['best_far_lag']) / 25:.2f} s) {'later' if coh['best_far_lag'] > 0 else 'earlier'} than the "
                 f"audio (r {coh['best_far_r']:.2f}; at lag 0 +- {coh['near_lag']}: {coh['r']:.2f}): the audio track seems "
                 "offset from the video; sync metrics and audio-driven training read it as it is")
    ctx.timed("speech_lips", t0, len(lms3d))
    return coh


def finish(ctx, info: decode.VideoInfo, sel, audio: np.ndarray, source: str, key: dict) -> None:
    """Audio, action units, the 25 fps video, meta.json and manifest.json."""
    t0 = time.perf_counter()
    src = source_frames(sel)
    n = len(src)
    runs = [(int(src[g.start]), int(src[g.stop - 1]) + 1) for g in track_mod.segments(src)]  # [a, b) source frames
    aud = np.concatenate([audio[a * SPF : b * SPF] for a, b in runs])
    write_wav(ctx.sub / "aud.wav", aud)
    from lmgs_eval.data.ingest.blink import au45

    aus = writer.action_units(sel["lms"])
    blink = au45(sel["mesh"]) if "mesh" in sel.files else np.full(n, np.nan)
    seen = np.isfinite(blink)  # frames without a mesh keep the eye aspect ratio's value
    aus["AU45_r"] = np.where(seen, blink, aus["AU45_r"])
    write_au_csv(ctx.sub / "au.csv", aus, sel["found"], writer.AU_COLUMNS)
    write_video(ctx.sub / f"{ctx.name}.mp4", (read_rgb_u8(ctx.sub / "ori_imgs" / f"{i}.jpg") for i in range(n)), 25, aud)
    ctx.timed("audio_video", t0, n)
    pz = np.load(ctx.work / "pose.npz")
    eul = np.degrees(pz["euler"])
    meta = {
        "bundled": False,
        "ingested": True,
        "ingest_version": INGEST_VERSION,
        "source": str(ctx.video),
        "au_csv": "AU45_r (blink): 5 x the mean of MediaPipe's eyeBlinkLeft / eyeBlinkRight blendshapes on the tracked face mesh "
                  "(the eye aspect ratio where no mesh was found); AU25_r / AU26_r from the lip gap and jaw drop: stand-ins for "
                  "OpenFace's intensities, not OpenFace's",
        "track_params": "euler = (pitch, yaw, roll) of the head in radians relative to facing the camera; trans = head position in the camera frame (OpenGL axes, metres); focal in pixels; no 3DMM id/exp",
        "lms3d": "2D landmarks lifted onto their camera rays at the depth of the fitted 68-point template (world = head frame, metres)",
        "parsing_colours": {"background": [255, 255, 255], "head": [255, 0, 0], "neck": [0, 255, 0], "torso": [0, 0, 255]},
        "teeth_mask": "inside of the inner-lip polygon (landmarks 60-67)",
        "depth_scale": 10000.0,
        "depth": "prior, not a measurement: camera z (metres) x depth_scale of a head-sized ellipsoid posed with the fitted head, inside the head mask; 0 elsewhere",
        "normal": "prior: camera-space unit normals (OpenCV axes) of the same ellipsoid, facing the camera; 0 elsewhere",
        "world_units": "metres; the head is fixed, the camera moves (ER-NeRF convention)",
    }
    write_json(ctx.sub / "meta.json", meta)
    manifest = {
        "ingest_version": INGEST_VERSION,
        "input": {"video": str(ctx.video), "sha256": key["input_sha256"], "bytes": ctx.video.stat().st_size, "probe": info.to_json()},
        "audio": {"source": source, "sha256": key["audio_sha256"], "seconds": round(len(aud) / 16000, 3)},
        "parameters": key["config"],
        "tools": writer.tool_versions(),
        "frames": {"kept": n, "first_source_frame": int(src[0]), "of": info.n_frames, "without_face": int((~sel["found"]).sum()),
                   "source_runs": [list(r) for r in runs]},
        "window": json.loads(str(sel["window"])),
        "pose": {"focal": float(pz["focal"]), "focal_widths": float(pz["focal"]) / ctx.cfg.size,
                 "focal_fit": json.loads(str(pz["focal_fit"])), "reprojection_px_mean": float(pz["reproj"].mean()),
                 "source": POSE_SOURCES.get(str(pz["source"]), str(pz["source"])) if "source" in pz.files else POSE_SOURCES["landmarks"],
                 **({"mesh_reprojection_px_mean": round(float(np.nanmean(pz["mesh_reproj"])), 3)}
                    if "mesh_reproj" in pz.files and np.isfinite(pz["mesh_reproj"]).any() else {}),
                 **({"texture_refinement": json.loads(str(pz["texture"]))} if "texture" in pz.files and str(pz["texture"]) != "{}" else {}),
                 "pitch_yaw_roll_deg_min": eul.min(0).round(2).tolist(), "pitch_yaw_roll_deg_max": eul.max(0).round(2).tolist(),
                 "scale": json.loads(str(pz["scale"]))},
        "flags": ctx.flags,
        "notes": ctx.log,
        "timings": ctx.timings,
    }
    manifest["speech_lips"] = speech_lips(ctx, aud, key)
    manifest["files"] = file_hashes(ctx.sub)
    write_json(ctx.sub / "manifest.json", manifest)
