"""``lmgs-eval bench model``: per-frame cost of the neural parts on this machine.

Times, per frame at inference: the audio path (Audio Encoder on the frame's 8-frame context +
attention smoother) and the deformation of N canonical Gaussians (landmark tri-plane
features, Spatial Enhancement, region attention, offset MLP, Landmark Compensation) as
``LMGSModel.render`` runs it (:meth:`~lmgs.deform.DeformNet.forward_prepared`: what does not
change from frame to frame computed once), beside the training-time forward with only the
canonical points' tri-plane features cached. Also the
tri-plane encoder's forward+backward on N points (a training step's share). Medians of
repeated runs, measured in this run, never compared with stored figures.

``frames`` rows follow one whole frame as ``LMGSModel.render`` makes it, at each image size:
audio (audio net), network (both branches' deformation), raster (both branches rasterized,
colour only) and compositing (face over mouth over the background, then to uint8).

``loss`` rows time a training step's image loss, L1 + D-SSIM and its backward, on a head
rendered over a background at each image size: as 3DGS's code computes it
(:func:`lmgs.losses.ssim_autograd`), with the closed-form gradient over the whole frame
(:func:`lmgs.losses.photometric`), and over the box around the head as training runs it
(:class:`lmgs.losses.CoveredPhotometric`).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import torch

HELP = "per-frame audio + deformation cost of the model's neural parts (5k / 10k Gaussians)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--points", type=int, nargs="+", default=[5000, 10000], help="Gaussian counts")
    p.add_argument("--repeats", type=int, default=30, help="timed runs per row (median reported)")
    p.add_argument("--preset", choices=["quick", "paper"], default="quick", help="config preset")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: leave as is)")
    p.add_argument("--sizes", type=int, nargs="+", default=[256, 512], help="image sizes of the per-frame breakdown")


def _median_ms(fn, repeats: int) -> float:
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def run(args: argparse.Namespace) -> dict:
    from lmgs.audio import AudioNet
    from lmgs.config import AudioConfig, DeformConfig, GuidanceConfig, TriplaneConfig
    from lmgs.deform import DeformNet

    if args.threads:
        torch.set_num_threads(args.threads)
    preset = args.preset
    acfg = getattr(AudioConfig, preset)()
    tcfg, gcfg, dcfg = getattr(TriplaneConfig, preset)(), getattr(GuidanceConfig, preset)(), getattr(DeformConfig, preset)()
    torch.manual_seed(0)
    C, W = (80, 16) if acfg.frontend in ("logmel", "mfcc") else (1024, 2)
    audio = AudioNet(C, W, acfg).eval()
    feats = torch.randn(100, W, C)
    idx = torch.tensor([50])
    rows = []
    with torch.no_grad():
        t_audio = _median_ms(lambda: audio(feats, idx), args.repeats)
    for n in args.points:
        xyz = torch.rand(n, 3) * 2 - 1
        lms = torch.rand(68, 3) * 2 - 1
        for name, g in (("full (SE+LC)", gcfg), ("no SE/LC", GuidanceConfig(se=False, lc=False))):
            face = DeformNet(acfg.dim, dcfg, tcfg, g).eval()
            with torch.no_grad():
                for p in face.parameters():  # trained-looking heads: the last layers start at zero
                    p.add_(torch.randn_like(p) * 0.05)
                cached = face.encode_points(xyz)
                prep = face.prepare(xyz, cached)
                fa = audio(feats, idx)[0]
                t_fwd = _median_ms(lambda: face(xyz, fa, lms, blink=0.3, point_features=cached), args.repeats)
                t_def = _median_ms(lambda: face.forward_prepared(prep, fa, lms, blink=0.3), args.repeats)
            rows.append(
                {
                    "points": n,
                    "guidance": name,
                    "audio_ms": round(t_audio, 3),
                    "deform_ms": round(t_def, 3),
                    "forward_ms": round(t_fwd, 3),
                    "prepared_speedup": round(t_fwd / t_def, 2),
                    "total_ms": round(t_audio + t_def, 3),
                    "frames_per_s": round(1e3 / (t_audio + t_def), 1),
                }
            )
        enc = face.encoder

        def step():
            enc.embeddings.grad = None
            (enc(xyz) ** 2).sum().backward()

        rows.append(
            {
                "points": n,
                "guidance": "triplane fwd+bwd",
                "audio_ms": None,
                "deform_ms": round(_median_ms(step, args.repeats), 3),
                "forward_ms": None,
                "prepared_speedup": None,
                "total_ms": None,
                "frames_per_s": None,
            }
        )
    frames = [frame_breakdown(n, res, audio, feats, idx, dcfg, tcfg, gcfg, args.repeats)
              for res in args.sizes for n in args.points]
    loss = [loss_breakdown(max(args.points), res, args.repeats) for res in args.sizes]
    return {
        "frames": frames,
        "loss": loss,
        "loss_note": "a training step's L1 + D-SSIM with its backward on a rendered head over a background: as 3DGS's "
                     "code computes it (autograd through padded depthwise convolutions), with the SSIM's gradient in "
                     "closed form over the whole frame, and over the box around the head as training runs it (the "
                     "same value and gradient); ms, medians of this run",
        "frames_note": "one frame as LMGSModel.render makes it: audio, network (face + mouth deformation), raster "
                       "(both branches, colour only), compositing (over the background, to uint8); the mouth branch "
                       "has a fifth of the face's Gaussians; untrained weights, a head-sized Gaussian blob",
        "preset": preset,
        "threads": torch.get_num_threads(),
        "triplane": f"{tcfg.n_levels} levels x {tcfg.n_features} features, table 2^{tcfg.log2_table_size}, res {tcfg.base_resolution}-{tcfg.finest_resolution}",
        "note": "rows: inference per frame as render runs it (deform_ms: DeformNet.forward_prepared, the per-point first "
                "layers computed once per clip) beside the training-time forward with the tri-plane features cached "
                "(forward_ms), measured in this run; no rasterization (see frames)",
        "rows": rows,
    }


def frame_breakdown(n: int, res: int, audio, feats, idx, dcfg, tcfg, gcfg, repeats: int) -> dict:
    """Median ms of each stage of one frame with ``n`` face Gaussians at ``res x res``."""
    from lmgs.config import GuidanceConfig
    from lmgs.deform import DeformNet
    from lmgs.model import composite
    from lmgs.render import rasterize
    from lmgs.render.bench import head_scene

    face_p, cam = head_scene(n, res, seed=0, requires_grad=False)
    mouth_p, _ = head_scene(max(1, n // 5), res, seed=1, requires_grad=False)
    lo, hi = face_p[0].min(0).values - 0.01, face_p[0].max(0).values + 0.01
    face_net = DeformNet(audio.out_dim, dcfg, tcfg, gcfg, lo, hi).eval()
    mouth_cfg = dataclasses.replace(dcfg, blink=False, exp_dim=0, position_only=True)  # the presets' mouth branch
    mouth_net = DeformNet(audio.out_dim, mouth_cfg, tcfg, GuidanceConfig(se=False, lc=False), lo, hi).eval()
    lms = torch.rand(gcfg.n_landmarks, 3) * (hi - lo) + lo
    bg = torch.rand(res, res, 3)
    with torch.no_grad():
        # what LMGSModel.render does: the per-point parts once per clip, then each frame
        face_f, mouth_f = face_net.prepare(face_p[0]), mouth_net.prepare(mouth_p[0])
        fa = audio(feats, idx)[0]

        def deformed(p, net, prep, landmarks, blink):
            o = net.forward_prepared(prep, fa, landmarks, blink)
            return p[0] + o.d_xyz, p[1] + o.d_rot, p[2] + o.d_scale, p[3], p[4]

        def network():
            return (deformed(face_p, face_net, face_f, lms if (gcfg.se or gcfg.lc) else None, 0.3),
                    deformed(mouth_p, mouth_net, mouth_f, None, None))

        fp, mp = network()

        def raster():
            return (rasterize(*fp, cam, None, render_mode="RGB"), rasterize(*mp, cam, None, render_mode="RGB"))

        face, mouth = raster()

        def compositing():
            rgb = composite(face, mouth, bg)[0]
            return (rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()

        ms = {
            "audio_ms": _median_ms(lambda: audio(feats, idx), repeats),
            "network_ms": _median_ms(network, repeats),
            "raster_ms": _median_ms(raster, repeats),
            "compositing_ms": _median_ms(compositing, repeats),
        }
    total = round(sum(ms.values()), 3)  # the printed total; the rate is of it
    return {"res": f"{res}x{res}", "points": n, **{k: round(v, 3) for k, v in ms.items()},
            "total_ms": total, "frames_per_s": round(1e3 / total, 1)}


def loss_breakdown(n: int, res: int, repeats: int) -> dict:
    """Median ms of the image loss and its backward for ``n`` Gaussians rendered at ``res x res``."""
    from lmgs import losses
    from lmgs.render import rasterize
    from lmgs.render.bench_scene import head_scene

    params, cam = head_scene(n, res, seed=0, requires_grad=False)
    g = torch.Generator().manual_seed(2)
    bg = torch.rand(res, res, 3, generator=g)
    with torch.no_grad():
        out = rasterize(*params, cam, None, render_mode="RGB")
    cover = out.alpha[..., 0] > 0
    img = (out.rgb + (1 - out.alpha) * bg).requires_grad_()
    frame = (bg * 0.8 + 0.2 * torch.rand(res, res, 3, generator=g)).clamp(0, 1)
    box = losses.CoveredPhotometric()

    def timed(loss_fn) -> float:
        def step():
            img.grad = None
            loss_fn().backward()

        return _median_ms(step, repeats)

    ms = {
        "autograd_ms": timed(lambda: losses.photometric(img, frame, ssim_fn=losses.ssim_autograd)),
        "closed_form_ms": timed(lambda: losses.photometric(img, frame)),
        "box_ms": timed(lambda: box(img, frame, bg, cover, key=0)),
    }

    def ratio(a: float, b: float) -> float | None:
        return round(a / b, 2) if b > 0 else None

    return {"res": f"{res}x{res}", "cover": round(float(cover.float().mean()), 3), **{k: round(v, 2) for k, v in ms.items()},
            "closed_form_speedup": ratio(ms["autograd_ms"], ms["closed_form_ms"]),
            "box_speedup": ratio(ms["autograd_ms"], ms["box_ms"])}
