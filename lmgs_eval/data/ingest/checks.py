"""What an ingest accepts: its version, the limits on its input, and the checks against them."""

from __future__ import annotations

from pathlib import Path

from lmgs_eval.data.ingest import decode
from lmgs_eval.errors import UserError

INGEST_VERSION = "11"  # 2: depth / normal priors; 3: the zoom check (pose.scale in the manifest); 4: head label on the jaw line, neck continued behind the head in torso_imgs, poses refined by tracked texture; 5: depth / normal priors cover the whole head mask; 6: the person's holes only where background does not reach the edge, the person grown against the plate; 7: the dense face mesh tracked, the focal length from it (a joint fit with a prior), AU45 from its blendshapes; 8: the person from the selfie segmenter, the head label beside the jaw, the soft rim in gt_imgs / torso_imgs only; 9: poses from the subject's shape fitted to the dense mesh, not smoothed over time (was a 2-frame Gaussian); 10: frames the tracked texture cannot refine carry their refined neighbours' correction (were all left unrefined below 90 % refinable); 11: the refinement is not kept where its poses turn less than 0.7 times as far as the poses it started from (align.MIN_FOLLOW), and the dense mesh's first detection made on a contiguous frame (dlib's first call on a decoder's padded view could miss the face)
MIN_SECONDS = 10.0  # shorter clips are ingested with a warning: too little to train on
MIN_FRAMES = 25  # fewer are refused: one second, which the first-10/11 split leaves 22 frames to train on and 3 to test
CUT_SHORT_WARN = 2 / 25  # seconds of the stated video that may not decode (rounding of the header); more: a warning...
CUT_SHORT_REFUSE = 0.1  # ...and above this share of the stated duration, a refusal: the file was cut short
MIN_FACE_PX = 100  # jaw width in source pixels under which the face is flagged as small
MOVING_SHARE = 0.02  # moving-camera flag: background residual above STATIC_LEVELS in more than this share...
STATIC_LEVELS = 10.0  # ...of the sampled frames (grey levels, median over the background)


def check_decoded(info: decode.VideoInfo) -> str | None:
    """Compare what decoded with what the file's header states: a file cut short by more than
    :data:`CUT_SHORT_REFUSE` of its video, or with as many corrupt frames, is refused; a smaller loss
    is returned as a warning (the subject is made from what decodes).

    Raises:
        UserError: the file is cut short or corrupt beyond repair.
    """
    miss, stated, n = info.missing_seconds, info.stated_duration, int(round(info.duration * info.fps))
    bad = info.corrupt_frames
    if stated and miss > CUT_SHORT_REFUSE * stated:
        raise UserError(f"{info.path}: the file is cut short: only {info.duration:.2f} s of the {stated:.2f} s of video its "
                        f"header states can be decoded ({miss / stated:.0%} missing); copy or export it again")
    if bad and bad > CUT_SHORT_REFUSE * max(n, 1):
        raise UserError(f"{info.path}: {bad} of {n} frames decode as corrupt; copy or export it again")
    said = []
    if miss > CUT_SHORT_WARN:
        said.append(f"the file is cut short: the last {miss:.2f} s of the {stated:.2f} s of video its header states "
                    "cannot be decoded")
    if bad:
        said.append(f"{bad} frames decode as corrupt")
    return f"{info.path}: {'; '.join(said)}; the subject is made from what decodes" if said else None


def check_length(video: Path, audio: Path | None, info: decode.VideoInfo, n_samples: int) -> None:
    """The video and the audio must each cover :data:`MIN_FRAMES` frames.

    Raises:
        UserError: naming the file that is too short and its length.
    """
    need = f"at least {MIN_FRAMES} frames at 25 fps, {MIN_FRAMES / 25:g} s"
    if info.n_frames < MIN_FRAMES:
        raise UserError(f"{video}: {info.n_frames} frame{'s' if info.n_frames != 1 else ''} at 25 fps ({info.duration:.2f} s): "
                        f"too few to make a subject ({need})")
    if n_samples // 640 < MIN_FRAMES:
        which = f"{audio}: the audio is" if audio is not None else f"{video}: its audio track is"
        raise UserError(f"{which} too short ({n_samples / 16000:.2f} s) to make a subject ({need}; "
                        f"the video has {info.duration:.2f} s)")


def check_frames(ctx, info: decode.VideoInfo, n_audio_frames: int, first: int, last: int,
                 left_out: tuple[int, ...] = ()) -> tuple[int, int]:
    """The frame range kept after the face coverage and the audio's length are taken into account
    (``left_out``: frames inside it without a face, which do not count towards the clip's length);
    ``ctx``: the ingest under way (its input files, and where its warnings go)."""
    if n_audio_frames < last:
        short = last - n_audio_frames
        if n_audio_frames - first < 1:
            raise UserError(f"{ctx.audio or ctx.video}: the audio ({n_audio_frames / 25:.2f} s) ends before the first frame with a face")
        ctx.warn("audio_shorter", f"the audio is {short} frames ({short / 25:.2f} s) shorter than the video; the last {short} frames are dropped")
        last = n_audio_frames
    kept = last - first - sum(1 for k in left_out if k < last)
    if kept < MIN_FRAMES:
        raise UserError(f"{ctx.video}: {kept} frame{'s' if kept != 1 else ''} with a face ({kept / 25:.2f} s): too few to make "
                        f"a subject (at least {MIN_FRAMES} frames at 25 fps, {MIN_FRAMES / 25:g} s)")
    if kept / 25 < MIN_SECONDS:
        ctx.warn("short_clip", f"{ctx.video}: {kept / 25:.1f} s with a face: too short to train a model well (at least {MIN_SECONDS:g} s; the field uses 3-5 min)")
    return first, last
