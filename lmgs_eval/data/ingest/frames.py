"""The per-frame work of the parsing, geometry and composite stages, run in chunks of frames.

Each function handles frames ``[a, b)`` of the subject folder ``sub`` and writes their files;
nothing depends on another chunk, so :func:`run_chunks` can spread the chunks over processes.
No frame's result depends on another's (the person segmenter has no state; each process loads
its own), so every file is the same for any number of processes.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from lmgs_eval.data.geometry import DEPTH_SCALE, render_prior
from lmgs_eval.data.images import read_rgb_u8, write_depth, write_normal, write_png, write_rgb
from lmgs_eval.data.ingest.parsing import Parts, mouth_mask, person_from, refine_person, split_parts, torso_layer, with_rim
from lmgs_eval.errors import UserError

CHUNK = 50  # frames per chunk


PNG_COMPRESSION = 1  # zlib level of the masks, parsing, normal and torso PNGs (lossless; 3-4x faster to write)


def parse(sub: Path, masks: Path, lms: np.ndarray, a: int, b: int, keep: frozenset) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The person masks of frames ``[a, b)`` (the segmenter's, :func:`parsing.person_from`), written
    into ``masks``; returns ``(k, frame, person)`` of the frames in ``keep`` (the plate's samples)."""
    from lmgs_eval.data.ingest.segment import segmenter

    seg = segmenter()
    out = []
    for i in range(a, b):
        img = read_rgb_u8(sub / "ori_imgs" / f"{i}.jpg")
        person = person_from(seg.probability(img), lms[i])
        write_png(masks / f"{i}.png", person.astype(np.uint8) * 255, PNG_COMPRESSION)
        if i in keep:
            out.append((i, img, person))
    return out


def refine(sub: Path, masks: Path, lms: np.ndarray, a: int, b: int) -> None:
    """Parsing maps and mouth masks of frames ``[a, b)``: the person split into head, neck and torso."""
    for i in range(a, b):
        person = read_rgb_u8(masks / f"{i}.png")[..., 0] > 127
        parts = split_parts(person, lms[i])
        write_png(sub / "parsing" / f"{i}.png", parts.colour_map(), PNG_COMPRESSION)
        np.save(sub / "teeth_mask" / f"{i}.npy", mouth_mask(lms[i], person.shape) & parts.head)


def geometry(sub: Path, w2c: np.ndarray, focal: float, centre: np.ndarray, axes: np.ndarray, a: int, b: int) -> None:
    """Depth and normal priors of frames ``[a, b)`` inside their head masks."""
    for i in range(a, b):
        p = read_rgb_u8(sub / "parsing" / f"{i}.png")
        h, w = p.shape[:2]
        depth, normal = render_prior(w2c[i], focal, w, h, centre, axes, np.all(p == (255, 0, 0), axis=-1))
        write_depth(sub / "depth" / f"{i}.png", depth, DEPTH_SCALE)
        write_normal(sub / "normal" / f"{i}.png", normal, dtype=np.float32, compression=PNG_COMPRESSION)


def composite(sub: Path, a: int, b: int) -> None:
    """``gt_imgs`` (the frame over the plate outside the person grown against the plate: its soft
    rim kept) and ``torso_imgs`` (RGBA; the rim beside the neck and torso with them)."""
    bc = read_rgb_u8(sub / "bc.jpg")
    for i in range(a, b):
        img = read_rgb_u8(sub / "ori_imgs" / f"{i}.jpg")
        parts = Parts.from_colour_map(read_rgb_u8(sub / "parsing" / f"{i}.png"))
        grown = refine_person(parts.person, img, bc)
        write_rgb(sub / "gt_imgs" / f"{i}.jpg", np.where(grown[..., None], img, bc))
        rgb, alpha = torso_layer(img, with_rim(parts, grown))
        rgba = np.concatenate([rgb, alpha[..., None].astype(np.uint8) * 255], -1)
        write_png(sub / "torso_imgs" / f"{i}.png", rgba, PNG_COMPRESSION)


def run_chunks(fn: Callable, n: int, args: tuple, jobs: int, bar=None) -> list:
    """``fn(*args, a, b, *rest)`` over chunks ``[a, b)`` of ``range(n)``, in ``jobs`` processes
    (spawned: a fresh interpreter, no threads inherited). Returns the results in chunk order."""
    spans = [(a, min(n, a + CHUNK)) for a in range(0, n, CHUNK)]
    if jobs <= 1 or len(spans) == 1:
        out = []
        for a, b in spans:
            out.append(fn(*args[0], a, b, *args[1]))
            if bar is not None:
                bar.update(b - a)
        return out
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    try:
        with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as ex:
            futs = [ex.submit(fn, *args[0], a, b, *args[1]) for a, b in spans]
            out = []
            for (a, b), f in zip(spans, futs):
                out.append(f.result())
                if bar is not None:
                    bar.update(b - a)
    except BrokenProcessPool:
        # a spawned worker died without a Python error: killed for memory, or it re-ran a script
        # that calls the ingest at its top level (spawn imports the main module again)
        raise UserError(f"{fn.__name__}: a worker process of the {jobs} stopped abruptly (out of memory, or a script "
                        "calling ingest() outside `if __name__ == \"__main__\":`); run again with --jobs 1 (jobs=1): "
                        "the ingest resumes after its last finished stage") from None
    return out
