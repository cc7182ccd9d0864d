"""The per-frame work of the parsing, geometry and composite stages, run in chunks of frames.

Each function handles frames ``[a, b)`` of the subject folder ``sub`` and writes their files;
nothing depends on another chunk, so :func:`run_chunks` can spread the chunks over processes
(:class:`Workers`: spawned once per ingest and kept for its stages).
No frame's result depends on another's (the person segmenter has no state; each process loads
its own), so every file is the same for any number of processes.

Speed: each worker process runs one thread of BLAS, OpenMP and OpenCV (the processes share the
cores; libraries that each start a thread per core fight over them and spin); the images the
stages pass between them are read and written in OpenCV's channel order where every operation
treats the channels alike, and the PNGs are written with zlib level 1 and the "up" row filter
(:func:`png_params`: lossless like every PNG setting, several times faster than level 1 with
OpenCV's adaptive filters, and smaller).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from lmgs_eval.data.geometry import DEPTH_SCALE, render_prior
from lmgs_eval.data.images import JPEG_QUALITY, read_rgb_u8
from lmgs_eval.data.ingest.parsing import Parts, mouth_mask, person_from, refine_person, split_parts, torso_layer, with_rim
from lmgs_eval.errors import UserError

CHUNK = 50  # frames per chunk


PNG_COMPRESSION = 1  # zlib level of every PNG the ingest writes (lossless)
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OPENCV_FOR_THREADS_NUM")  # 1 in a worker


def png_params() -> list[int]:
    """OpenCV's PNG parameters of the ingest's PNGs: zlib level :data:`PNG_COMPRESSION` and the
    "up" filter on every row (where this OpenCV lets one choose the filter)."""
    import cv2

    out = [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION]
    if hasattr(cv2, "IMWRITE_PNG_FILTER"):
        out += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]
    return out


def _write_png(path: Path, data: np.ndarray) -> None:
    """A PNG of ``data`` as OpenCV takes it: grey ``[H, W]`` (uint8 or uint16), BGR or BGRA."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(data), png_params())
    if not ok:
        raise UserError(f"{path}: could not encode a PNG")
    try:
        Path(path).write_bytes(buf.tobytes())
    except OSError as exc:
        raise UserError(f"{path}: could not write image ({exc.strerror})") from None


def _read(path: Path, flags: int | None = None) -> np.ndarray:
    """An image as OpenCV reads it (BGR by default); a missing or unreadable file is a :class:`UserError`."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR if flags is None else flags)
    if img is None:
        why = "not a readable image (corrupt or wrong format)" if Path(path).exists() else "file not found"
        raise UserError(f"{path}: {why}")
    return img


def parse(sub: Path, masks: Path, lms: np.ndarray, a: int, b: int, keep: frozenset) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The person masks of frames ``[a, b)`` (the segmenter's, :func:`parsing.person_from`), written
    into ``masks``; returns ``(k, frame, person)`` of the frames in ``keep`` (the plate's samples)."""
    from lmgs_eval.data.ingest.segment import segmenter

    seg = segmenter()
    out = []
    for i in range(a, b):
        img = read_rgb_u8(sub / "ori_imgs" / f"{i}.jpg")
        person = person_from(seg.probability(img), lms[i])
        _write_png(masks / f"{i}.png", person.view(np.uint8) * np.uint8(255))
        if i in keep:
            out.append((i, img, person))
    return out


def refine(sub: Path, masks: Path, lms: np.ndarray, a: int, b: int) -> None:
    """Parsing maps and mouth masks of frames ``[a, b)``: the person split into head, neck and torso."""
    import cv2

    for i in range(a, b):
        person = _read(masks / f"{i}.png", cv2.IMREAD_GRAYSCALE) > 127
        parts = split_parts(person, lms[i])
        _write_png(sub / "parsing" / f"{i}.png", parts.colour_map(bgr=True))
        np.save(sub / "teeth_mask" / f"{i}.npy", mouth_mask(lms[i], person.shape) & parts.head)


def geometry(sub: Path, w2c: np.ndarray, focal: float, centre: np.ndarray, axes: np.ndarray, a: int, b: int,
             face: Path | None = None) -> None:
    """Depth and normal priors of frames ``[a, b)`` inside their head masks: the tracked face
    mesh where it covers the head (``face``: a ``.npy`` of its vertices in camera coordinates
    ``[N, 468, 3]``, :func:`pose.lift_mesh`; NaN where a frame has none), the head ellipsoid and
    the sheet through its outline elsewhere (:func:`lmgs_eval.data.geometry.render_prior`).

    The maps are encoded as :func:`lmgs_eval.data.images.write_depth` and ``write_normal``
    (float32) encode them, the same values, but only over the head mask: the priors are 0
    everywhere else, which both encode as 0."""
    from lmgs_eval.data.geometry import render_mesh
    from lmgs_eval.data.ingest.focal import canonical_triangles

    verts = np.load(face, mmap_mode="r") if face is not None else None
    tris = canonical_triangles() if face is not None else None
    for i in range(a, b):
        head = Parts.from_colour_map(_read(sub / "parsing" / f"{i}.png"), bgr=True).head
        h, w = head.shape
        depth, normal = render_prior(w2c[i], focal, w, h, centre, axes, head)
        if verts is not None and np.isfinite(verts[i]).all():
            d_face, n_face = render_mesh(np.asarray(verts[i]), tris, focal, w, h)
            on = head & (d_face > 0)
            depth[on], normal[on] = d_face[on], n_face[on]
        d16 = np.zeros((h, w), np.uint16)
        d16[head] = np.clip(np.rint(depth[head].astype(np.float64) * DEPTH_SCALE), 0, 65535).astype(np.uint16)
        _write_png(sub / "depth" / f"{i}.png", d16)
        n = normal[head]  # float32 [M, 3]
        valid = np.linalg.norm(n, axis=1, keepdims=True) > 0.5
        enc = np.zeros((h, w, 3), np.uint8)
        enc[head] = np.where(valid, np.clip(np.rint((n + 1.0) * 127.5), 0, 255), 0).astype(np.uint8)[:, ::-1]  # as BGR
        _write_png(sub / "normal" / f"{i}.png", enc)


def composite(sub: Path, a: int, b: int) -> None:
    """``gt_imgs`` (the frame over the plate outside the person grown against the plate: its soft
    rim kept) and ``torso_imgs`` (RGBA; the rim beside the neck and torso with them).

    The frames stay in OpenCV's BGR order throughout: the growth, the torso layer and the
    compositing treat the three channels alike."""
    import cv2

    bc = _read(sub / "bc.jpg")
    for i in range(a, b):
        img = _read(sub / "ori_imgs" / f"{i}.jpg")
        parts = Parts.from_colour_map(_read(sub / "parsing" / f"{i}.png"), bgr=True)
        grown = refine_person(parts.person, img, bc)
        gt = bc.copy()
        np.copyto(gt, img, where=grown[..., None])
        if not cv2.imwrite(str(sub / "gt_imgs" / f"{i}.jpg"), gt, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
            raise UserError(f"{sub / 'gt_imgs' / f'{i}.jpg'}: could not write image")
        rgb, alpha = torso_layer(img, with_rim(parts, grown))
        _write_png(sub / "torso_imgs" / f"{i}.png", np.dstack([rgb, alpha.view(np.uint8) * np.uint8(255)]))


def _init_worker() -> None:
    """In each worker process: OpenCV on one thread (BLAS and OpenMP read :data:`THREAD_ENV` when they load)."""
    import cv2

    cv2.setNumThreads(1)


def _ready() -> None:
    return None


@contextmanager
def _one_thread_env():
    """:data:`THREAD_ENV` set to 1 while processes are spawned (they inherit it), restored after."""
    saved = {k: os.environ.get(k) for k in THREAD_ENV}
    os.environ.update({k: "1" for k in THREAD_ENV})
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class Workers:
    """``jobs`` spawned worker processes (a fresh interpreter each, no threads inherited), kept for
    every stage of one ingest: each pays its imports (seconds) and loads its models once, not
    once per stage. :meth:`start` spawns them at once, so that they start up while the main
    process works; a ``with`` block or :meth:`close` ends them."""

    def __init__(self, jobs: int) -> None:
        self.jobs = int(jobs)
        self._ex = None

    def start(self) -> "Workers":
        self.executor()
        return self

    def executor(self):
        if self._ex is None:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            with _one_thread_env():
                ex = ProcessPoolExecutor(max_workers=self.jobs, mp_context=mp.get_context("spawn"), initializer=_init_worker)
                for _ in range(self.jobs):  # a process is spawned per task submitted while none is idle
                    ex.submit(_ready)
            self._ex = ex
        return self._ex

    def close(self) -> None:
        if self._ex is not None:
            ex, self._ex = self._ex, None
            ex.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "Workers":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def run_chunks(fn: Callable, n: int, args: tuple, jobs: int, bar=None, workers: Workers | None = None) -> list:
    """``fn(*args, a, b, *rest)`` over chunks ``[a, b)`` of ``range(n)``, in ``jobs`` processes
    (``workers``' when given, else spawned for this call: :class:`Workers`). Returns the
    results in chunk order."""
    spans = [(a, min(n, a + CHUNK)) for a in range(0, n, CHUNK)]
    if jobs <= 1 or len(spans) == 1:
        out = []
        for a, b in spans:
            out.append(fn(*args[0], a, b, *args[1]))
            if bar is not None:
                bar.update(b - a)
        return out
    from concurrent.futures.process import BrokenProcessPool

    own = workers is None
    pool = Workers(jobs) if own else workers
    try:
        ex = pool.executor()
        futs = [ex.submit(fn, *args[0], a, b, *args[1]) for a, b in spans]
        out = []
        for (a, b), f in zip(spans, futs):
            out.append(f.result())
            if bar is not None:
                bar.update(b - a)
    except BrokenProcessPool:
        # a spawned worker died without a Python error: killed for memory, or it re-ran a script
        # that calls the ingest at its top level (spawn imports the main module again)
        pool.close()
        raise UserError(f"{fn.__name__}: a worker process of the {pool.jobs} stopped abruptly (out of memory, or a script "
                        "calling ingest() outside `if __name__ == \"__main__\":`); run again with --jobs 1 (jobs=1): "
                        "the ingest resumes after its last finished stage") from None
    finally:
        if own:
            pool.close()
    return out
