"""The benchmark as a static site, made only from a results store: ``build_site(store, out)``.

Pages (Jinja2 templates in ``templates/``, plain JavaScript and CSS in ``static/``; no server,
no network: the site opens from disk or any static host):

* ``index.html``: subjects and protocols, the status of every method x subject, what was skipped;
* ``board-<subject>.html``: every table's section about the subject (Table I / II values with
  bootstrap CIs, significance marks, § busy-host and ‡ mixed-backend flags, stand-ins), each
  sortable by any column, rows filtered by method family;
* ``watch-<subject>-<clip>.html``: the ground truth and the chosen methods in lockstep (one
  play / pause / seek, frame stepping, the clip's audio), error maps ``|render - GT|``, the
  per-frame metric curves (``per_item``) with a cursor, the worst frames of each method;
* ``charts.html``: speed against accuracy (Pareto front, hover card with runs and config
  hashes), capacity, stability and calibration, with the static PNG / SVG for papers;
* ``runs/<id>.html``: provenance of one run (config and hash, commit, machine and CPU kernels,
  metric backends and weights sha256, stand-ins, cost breakdown) linking its record JSON.

Every number is a cell of :func:`lmgs_eval.report.tables.all_tables` or a record field; video
previews are made by :mod:`lmgs_eval.report.site.media` from the renders the records name.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from lmgs_eval.errors import UserError
from lmgs_eval.paths import atomic_dir, check_out_dir
from lmgs_eval.report.site.model import (CURVE_METRICS, FILTER_FAMILIES, MARKS_LEGEND, WatchRun, curve_meta, curves, leaderboards,
                                         make_runs, watch_groups)
from lmgs_eval.results.store import iter_store, resolve_artefact
from lmgs_eval.results.types import Record

HERE = Path(__file__).resolve().parent
INDEX = "index.html"


def _slug(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", s).strip("._") or "x"


def _env():
    import jinja2

    env = jinja2.Environment(loader=jinja2.FileSystemLoader(str(HERE / "templates")),
                             autoescape=jinja2.select_autoescape(["html", "j2"]), trim_blocks=True,
                             lstrip_blocks=True, undefined=jinja2.ChainableUndefined, keep_trailing_newline=True)
    env.filters["slug"] = _slug
    env.filters["pretty"] = lambda v: json.dumps(v, indent=1, sort_keys=True, ensure_ascii=False)
    env.filters["num"] = lambda v, d=3: "–" if v is None else (f"{v:.{d}f}" if isinstance(v, float) else str(v))
    return env


def build_site(store: str | os.PathLike, out: str | os.PathLike, previews: bool = True,
               charts: bool = True, renders: str | os.PathLike | None = None, preview_side: int = 256,
               log: Callable[[str], None] = lambda s: None) -> tuple[Path, list[str]]:
    """Write the site for results store ``store`` into folder ``out`` (replaced atomically).

    Args:
        store: the results store (a folder of records; renders relative to it).
        out: the site's folder; an older site there is replaced, its video previews reused.
        previews: encode video previews of the renders found on this machine.
        charts: write the static PNG / SVG charts (matplotlib) beside the interactive ones.
        renders: the folder that records' relative render paths are under (default ``store``): a
            snapshot of records (``tables/records``) with the store that made them.
        preview_side: the longer side of the video previews, in pixels.
        log: called with one line per step.

    Returns:
        The index page's path and one warning per record file that was skipped.

    Raises:
        UserError: ``store`` is not a folder or holds no valid record; ``renders`` is not a folder;
            ``out`` is a file, the store or above it, a folder that is neither empty nor an earlier
            report (it is replaced whole), or one that cannot be made or written.
    """
    store, out = Path(store), Path(out)
    if not store.is_dir():
        raise UserError(f"--results {store}: not a folder of result records")
    if renders is not None and not Path(renders).is_dir():
        raise UserError(f"--renders {renders}: " + ("is a file, not the folder the records' renders are under"
                                                    if Path(renders).exists() else "no such folder"))
    items, warnings = iter_store(store)
    if not items:
        raise UserError(f"--results {store}: no valid result record in it (run `lmgs-eval self` first)")
    if out.resolve() == store.resolve() or out.resolve() in store.resolve().parents:
        raise UserError(f"--out {out}: would replace the results store {store}; choose a folder inside or beside it")
    _check_out(out)
    from lmgs_eval.report.tables import all_tables

    runs = make_runs(items, store)
    records = [r.record for r in runs]
    run_ids = {id(r.record): r.id for r in runs}
    tables = all_tables(records)
    boards = leaderboards(tables, run_ids)
    groups = watch_groups(runs)
    env = _env()
    subjects = sorted({r.subject.name for r in records})
    old_media = out / "media" if (out / "media").is_dir() else None
    with atomic_dir(out) as tmp:
        shutil.copytree(HERE / "static", tmp / "static")
        (tmp / MARKER).write_text("made by lmgs-eval report; this folder is replaced whole when the report is rebuilt\n")
        # atomic_dir removes the old site only once this one is written: its previews can be reused
        watches = _watch_players(tmp, out, Path(renders) if renders is not None else store, groups, previews, old_media,
                                 preview_side, log)
        static_files = _static_charts(records, tmp, log) if charts else []
        from lmgs_eval.report.site.svgcharts import capacity_svgs, speed_charts_svg

        common = {"subjects": subjects, "watches": watches, "n_runs": len(runs), "store": str(store),
                  "families": [f for f in FILTER_FAMILIES if any(r.method.family == f for r in records)]}
        page = lambda name, tpl, **kw: (tmp / name).write_text(  # noqa: E731
            env.get_template(tpl).render(**common, **kw), encoding="utf-8")
        page(INDEX, "index.html.j2", title="Benchmark report", status=boards.get("", []), warnings=warnings,
             protocols=_protocol_counts(records))
        for s in subjects:
            page(f"board-{_slug(s)}.html", "board.html.j2", title=f"Leaderboard: {s}", subject=s,
                 tables=boards.get(s, []), legend=MARKS_LEGEND)
        svg = speed_charts_svg(records, run_ids)
        for c in svg:
            c["png"] = f"charts/{c['static']}.png" if (tmp / "charts" / f"{c['static']}.png").is_file() else None
        calibration = [t for s in subjects for t in boards.get(s, []) if t.id.startswith("calibration")]
        stability = [t for s in subjects for t in boards.get(s, []) if t.id.startswith("stability")]
        page("charts.html", "charts.html.j2", title="Charts", charts=svg, static=static_files,
             capacity=capacity_svgs(records, run_ids),
             calibration=calibration, stability=stability)
        for w in watches:
            page(w["file"], "watch.html.j2", title=f"Watch: {w['subject']} ({w['protocol']}, {w['clip']})", **w)
        (tmp / "runs").mkdir()
        tpl = env.get_template("run.html.j2")
        for run in runs:
            rel_json = os.path.relpath(run.path.resolve(), (out / "runs").resolve())
            arts = [{"role": role, "path": a.path, "sha256": a.sha256,
                     "here": resolve_artefact(renders if renders is not None else store, a.path).is_file()}
                    for role, a in sorted(run.record.artefacts.items())]
            # the page lists the record's fields as its JSON holds them
            (tmp / "runs" / f"{run.id}.html").write_text(
                tpl.render(**common, title=f"Run {run.label} / {run.record.subject.name}", run=run,
                           rec=run.record.to_dict(), record_json=Path(rel_json).as_posix(), artefacts=arts, root="../"),
                encoding="utf-8")
    log(f"[report] {len(runs)} runs, {len(subjects)} subject(s) -> {out / INDEX}")
    return out / INDEX, warnings


MARKER = ".lmgs-report"
"""A file every site has: an existing ``--out`` folder is replaced only when it holds one (or nothing)."""


def _check_out(out: Path) -> None:
    """The site replaces ``out`` whole: refuse a file, or a folder that is not an earlier site and not empty."""
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: is a file, not a folder for the report")
    if out.is_dir() and not (out / MARKER).is_file() and any(out.iterdir()):
        raise UserError(f"--out {out}: folder exists and is not a report made by `lmgs-eval report` (it would be "
                        "replaced whole); choose a new folder")
    check_out_dir(out, "--out")


def _protocol_counts(records: list[Record]) -> list[dict[str, Any]]:
    counts: dict[tuple[str, str], int] = {}
    for r in records:
        key = (r.subject.name, r.protocol.name)
        counts[key] = counts.get(key, 0) + 1
    return [{"subject": s, "protocol": p, "runs": n} for (s, p), n in sorted(counts.items())]


def _watch_players(tmp: Path, out: Path, store: Path, groups: dict, previews: bool, reuse: Path | None,
                   side: int, log: Callable[[str], None]) -> list[dict[str, Any]]:
    """One Watch page's context per (subject, protocol, clip), its previews written under ``tmp/media``."""
    from lmgs_eval.report.site.media import ERROR_GAIN, Previews

    made = Previews(store, tmp / "media", reuse=reuse, max_side=side)
    pages = []
    for (subject, protocol, clip), by_method in groups.items():
        gt = next((r for r in by_method.values() if r.record.method.family == "ground-truth"), None)
        players = []
        carrier = None  # the player whose preview has the sound: the ground truth, else the first with a render
        for run in by_method.values():
            w = WatchRun(run, curves(run.record))
            is_gt = run is gt
            full = made.full(run.record)
            if full is not None:  # the render itself, where it lies (relative: the site and store move together)
                w.full = Path(os.path.relpath(full.resolve(), out.resolve())).as_posix()
            if previews:
                w.audio = is_gt or (gt is None and carrier is None and full is not None)
                w.video, w.missing = made.preview(run.record, audio=w.audio)
                if w.video and w.audio:
                    carrier = run
                if w.video and gt is not None and not is_gt:
                    w.error, w.note = made.error(run.record, gt.record)
            else:
                w.missing = "previews not made (--no-previews)"
            log(f"[report] watch {subject}/{clip}: {run.label}: {w.video or w.missing}")
            players.append(w)
        name = f"watch-{_slug(subject)}-{_slug(clip) if protocol == 'self' else _slug(protocol + '-' + clip)}.html"
        n_frames = next((r.record.protocol.n_frames for r in by_method.values() if r.record.protocol.n_frames), None)
        data = {"fps": made.fps or 25.0, "n_frames": n_frames, "metrics": curve_meta(), "order": list(CURVE_METRICS),
                "gain": ERROR_GAIN,
                "players": [{"id": w.run.id, "label": w.run.label, "family": w.run.record.method.family,
                             "gt": w.run is gt, "video": w.video, "error": w.error, "missing": w.missing, "full": w.full,
                             "audio": w.audio, "note": w.note,
                             "seed": w.run.record.seed, "config_hash": w.run.record.config_hash,
                             "curves": w.curves} for w in players]}
        pages.append({"subject": subject, "clip": clip, "protocol": protocol, "file": name, "players": players,
                      "data": data, "with_video": sum(1 for w in players if w.video)})
    return pages


def _static_charts(records: list[Record], tmp: Path, log: Callable[[str], None]) -> list[str]:
    """The matplotlib charts (PNG, and SVG where made) under ``charts/``; site-relative paths of the PNGs."""
    from lmgs_eval.report.charts import all_charts

    files = all_charts(records, tmp / "charts")
    for p in files:  # the site keeps the PNGs; the SVGs for papers are `lmgs-eval table`'s
        if p.suffix == ".svg":
            p.unlink()
    log(f"[report] {sum(p.suffix == '.png' for p in files)} static charts")
    # the speed charts are drawn interactive on the page (their PNG / SVG are linked from there)
    return sorted(p.relative_to(tmp).as_posix() for p in files
                  if p.suffix == ".png" and not p.name.startswith(("speed_", "train_")))


__all__ = ["INDEX", "build_site"]
