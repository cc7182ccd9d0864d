"""The static report site from a hand-written store with real renders: pages, previews, error maps, and
(in headless Chromium, when it is installed) sorting, filtering, lockstep players and the metric cursor."""

from __future__ import annotations

import html
import re
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli
from lmgs.fileio import sha256_file
from lmgs_eval.results import write_record
from test_results import N_ITEMS, fixture_records

FPS = 25
SIZE = 64
GT_LEVEL, RENDERED = 0.5, {"lmgs": 0.55, "talkinggaussian": 0.65}  # flat offsets from the ground truth


def _frames(level: float) -> np.ndarray:
    """``N_ITEMS`` frames: a flat grey ``level`` with a white square moving one step a frame (uint8)."""
    f = np.full((N_ITEMS, SIZE, SIZE, 3), level, np.float32)
    for i in range(N_ITEMS):
        f[i, 4:14, 2 + 2 * i: 12 + 2 * i] = 1.0
    return (f * 255).round().astype(np.uint8)


def _store(root: Path) -> list[dict]:
    """The tables' fixture store, with renders for the ground truth and two methods (seed 0); ER-NeRF's is absent."""
    from lmgs_eval.data.video import write_video

    recs = fixture_records()
    t = np.arange(N_ITEMS * 640) / 16000
    audio = 0.2 * np.sin(2 * np.pi * 220 * t)
    for r in recs:
        name = r["method"]["name"]
        if r["protocol"]["name"] != "self" or r["seed"] != 0 or name not in ("gt", "lmgs", "talkinggaussian", "ernerf"):
            continue
        rel = f"renders/{name}.mp4"
        if name != "ernerf":
            level = GT_LEVEL if name == "gt" else RENDERED[name]
            write_video(root / rel, _frames(level), fps=FPS, audio=audio if name == "gt" else None)
        sha = sha256_file(root / rel) if name != "ernerf" else "e" * 64
        r["artefacts"] = {"render": {"path": rel, "sha256": sha}}
        if name == "talkinggaussian":
            r["cost"]["others_cpu_share"] = 0.4  # timed while other processes took 40% of the CPU: marked §
    for r in recs:
        write_record(root, r)
    return recs


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    from lmgs_eval.report.site import build_site

    root = tmp_path_factory.mktemp("report")
    _store(root / "results")
    index, warnings = build_site(root / "results", root / "results" / "report", charts=False)
    assert warnings == []
    return index.parent


def _decode(path: Path) -> tuple[np.ndarray, list[str], list[str]]:
    import av

    with av.open(str(path)) as c:
        codecs = [s.codec_context.name for s in c.streams.video]
        audio = [s.codec_context.name for s in c.streams.audio]
        frames = np.stack([f.to_ndarray(format="rgb24") for f in c.decode(video=0)])
    return frames, codecs, audio


# ----------------------------------------------------------------------------- without a browser
def test_the_site_has_every_page_type(site):
    names = {p.name for p in site.iterdir()}
    assert {"index.html", "board-astronaut.html", "watch-astronaut-test.html", "charts.html", "runs", "static",
            "media"} <= names
    # one page per record, named by subject, protocol, method, clip, seed and config hash, holding
    # that record's method, config hash and every metric value (4 decimals; "–" for none)
    recs = fixture_records()
    pages = {f"{r['subject']['name']}__{r['protocol']['name']}__{r['method']['name']}--{r['protocol']['clip']}"
             f"--seed{r['seed']}--{r['config_hash']}.html": r for r in recs}
    assert len(pages) == len(recs) and sorted(p.name for p in (site / "runs").iterdir() if p.suffix == ".html") == sorted(pages)
    for name, r in pages.items():
        text = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", html.unescape((site / "runs" / name).read_text())))
        assert f"Run {r['method']['display_name']} / {r['subject']['name']}" in text and r["config_hash"] in text, name
        for k, e in r["metrics"].items():
            v = e["value"]
            shown = "–" if v is None else f"{v:.4f}" if isinstance(v, float) else str(v)
            assert f" {k}{'↑' if e['higher_is_better'] else '↓'} {shown} " in text, (name, k, shown)
    index = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", html.unescape((site / "index.html").read_text())))
    assert f"{len(recs)} runs on 1 subject(s)" in index
    for proto in ("cross", "self", "stress"):
        assert f"{proto} {sum(r['protocol']['name'] == proto for r in recs)} runs" in index, proto
    watch = (site / "watch-astronaut-test.html").read_text()
    for src in re.findall(r'<(?:script|link)[^>]+(?:src|href)="([^"]+)"', watch):  # nothing from the network
        assert not src.startswith(("http:", "https:", "//")), src
        assert src.startswith("data:") or (site / src).is_file(), src


def test_previews_are_h264_and_the_error_map_is_the_gained_absolute_difference(site):
    watch = (site / "watch-astronaut-test.html").read_text()
    videos = re.findall(r'<video class="(main|err)[^"]*" src="([^"]+)"', watch)
    mains = [s for k, s in videos if k == "main"]
    errs = [s for k, s in videos if k == "err"]
    assert len(mains) == 3 and len(errs) == 2  # ground truth, lmgs, TalkingGaussian; error maps for the two methods
    gt, codecs, audio = _decode(site / mains[0])
    assert codecs == ["h264"] and audio == ["aac"] and gt.shape == (N_ITEMS, SIZE, SIZE, 3)
    for src in errs:
        err, codecs, audio = _decode(site / src)
        assert codecs == ["h264"] and audio == []
        # |render - GT| x 4 of the render files as decoded here, on the flat background
        name = [k for k in RENDERED if k in watch.split(src)[0].rsplit("data-id", 1)[-1]]
        assert len(name) == 1
        r = _decode(site.parent / "renders" / f"{name[0]}.mp4")[0].astype(float)
        g = _decode(site.parent / "renders" / "gt.mp4")[0].astype(float)
        want = np.clip(4 * np.abs(r - g).mean(-1), 0, 255)[:, 40:60, 10:50]
        assert 30 < want.mean() < 200  # a grey well inside the range: the gain is tested, not clipping
        bg = err[:, 40:60, 10:50, 0].astype(float)
        assert np.abs(bg - want).mean() < 3, (bg.mean(), want.mean())


def test_previews_are_downscaled_to_the_side_asked_for(site, tmp_path):
    import shutil

    from lmgs_eval.report.site import build_site

    store = tmp_path / "results"
    shutil.copytree(site.parent, store, ignore=shutil.ignore_patterns("report"))
    index, _ = build_site(store, tmp_path / "site", charts=False, preview_side=32)
    for f in (index.parent / "media").iterdir():
        assert _decode(f)[0].shape[1:3] == (32, 32), f.name


def test_a_run_whose_render_is_elsewhere_says_so_on_its_player(site):
    watch = html.unescape((site / "watch-astronaut-test.html").read_text())
    block = watch.split('data-id="astronaut__self__ernerf--test--seed0')[1].split("</figure>")[0]
    assert "render not on this machine (renders/ernerf.mp4" in block
    assert "<video" not in block


def test_leaderboard_cells_are_the_tables_cells(site):
    from lmgs_eval.report.tables import table_self
    from lmgs_eval.results import load_records

    recs, _ = load_records(site.parent)
    t1 = table_self(recs)
    board = html.unescape((site / "board-astronaut.html").read_text())
    md = t1.markdown()
    ours = next(line for line in md.splitlines() if line.startswith("| Ours (lmgs)"))
    psnr = re.sub(r"[*<>/u]", "", ours.split("|")[2]).strip()  # e.g. 38.04 ± 0.05, bold / underline removed
    assert psnr in board
    # the CI of the cell, as the CSV gives it
    cell = t1.sections[0].rows[-1].cells["psnr"]
    assert f"[{cell.ci.lo:.2f}, {cell.ci.hi:.2f}]" in board
    assert '<span class="standin"' in board
    table1 = board.split('id="table1_self-0"')[1].split("</section>")[0]
    rows = {m.group(1): m.group(0) for m in re.finditer(r'<td class="label" data-sort="([^"]+)">.*?</tr>', table1, re.S)}
    assert '<span class="flag">§</span>' in rows["TalkingGaussian"]
    assert '<span class="flag">§</span>' not in rows["Ours (lmgs)"]


def test_run_page_carries_the_provenance(site):
    page = html.unescape((site / "runs" / "astronaut__self__lmgs--test--seed0--{}.html".format(
        next(r for r in fixture_records() if r["method"]["name"] == "lmgs")["config_hash"])).read_text())
    for text in ("Test CPU", "0" * 40, "onnxruntime:bundled-sync", "ST-LPIPS (shift-tolerant)", "fps", "theta"):
        assert text in page, text
    link = re.search(r'<a href="([^"]+)">record JSON</a>', page).group(1)
    assert (site / "runs" / link).resolve().is_file()


def test_a_rebuild_reuses_previews_of_the_same_renders(site, tmp_path, monkeypatch):
    import shutil

    from lmgs_eval.report.site import build_site, media

    store = tmp_path / "results"
    shutil.copytree(site.parent, store)
    before = {p.name: p.read_bytes() for p in (store / "report" / "media").iterdir()}
    monkeypatch.setattr(media, "_encode", lambda *a, **k: pytest.fail("re-encoded a preview"))
    build_site(store, store / "report", charts=False)
    assert {p.name: p.read_bytes() for p in (store / "report" / "media").iterdir()} == before


def test_each_driving_clip_has_a_watch_page_without_ground_truth(site):
    for clip in ("A", "B"):
        page = html.unescape((site / f"watch-astronaut-cross-{clip}.html").read_text())
        ids = re.findall(r'<figure class="player[^"]*" data-id="([^"]+)"', page)
        assert sorted(i.split("__")[2].split("--")[0] for i in ids) == ["ernerf", "lmgs", "talkinggaussian"]
        assert all(f"--{clip}--seed0--" in i for i in ids)
        assert 'id="errmap"' not in page and "Ground Truth" not in page.split('id="players"')[1]
        players = page.split('id="players"')[1].split('id="watch-data"')[0]
        assert players.count("this run recorded no render") == 3


def test_capacity_panels_mark_the_knee_and_name_each_budgets_runs():
    from lmgs_eval.report.capacity import budget_means, knee, points_from_records
    from lmgs_eval.report.site.svgcharts import capacity_svgs
    from test_results import items, metric, record, typed

    recs = []
    for b, (psnr, fps) in {500: (30.0, 90.0), 2000: (33.0, 60.0), 8000: (33.1, 30.0)}.items():
        for seed in (0, 1):
            recs.append(record("lmgs", "Ours (lmgs)", "3DGS", seed, {"psnr": metric("psnr", items(psnr, 0.2, b + seed))},
                               protocol="capacity", clip=f"budget-{b}", config={"budget": b},
                               cost={"fps": fps, "n_gaussians": b}))
    recs = typed(recs)
    ids = {id(r): f"run{k}" for k, r in enumerate(recs)}
    (cap,) = capacity_svgs(recs, ids)
    want = knee(budget_means(points_from_records(recs)["astronaut"]))
    assert want["budget"] == 2000 and cap["knee"] == "2000 Gaussians (budget 2000)"  # within 0.3 dB of the best
    svg = html.unescape(cap["svg"])
    assert svg.count("<svg") == 2  # PSNR and FPS: the panels the records have values for
    assert svg.count('<g class="pt"') == 6 and svg.count("knee:") == 2
    assert "budget 8000, 2 seed(s)" in svg and "runs: run4, run5" in svg
    # each point sits at its budget on a log axis and at its mean over the seeds on the value axis,
    # as read back through the panel's own tick marks; higher values higher up; the knee at 2000
    for panel, means in zip(svg.split("<svg")[1:], ([30.0, 33.0, 33.1], [90.0, 60.0, 30.0])):
        grid = [(float(v), float(y)) for v, y in re.findall(r'<text x="[^"]+" y="[^"]+" class="tick" text-anchor="end">'
                                                          r'([^<]+)</text><line x1="[^"]+" y1="([^"]+)"', panel)]
        (v0, y0), (v1, y1) = grid[0], grid[-1]
        assert v1 > v0 and y1 < y0  # the value axis grows upwards
        xt = {t: float(x) for x, t in re.findall(r'<text x="([^"]+)" y="[^"]+" class="tick" text-anchor="middle">'
                                                 r'([0-9.k]+)</text>', panel)}
        pts = [(float(x), float(y)) for x, y in re.findall(r'<circle cx="([^"]+)" cy="([^"]+)"', panel)]
        assert [x for x, _ in pts] == [xt["500"], xt["2.0k"], xt["8.0k"]]
        assert pts[1][0] - pts[0][0] == pytest.approx(pts[2][0] - pts[1][0], abs=0.15)  # 4x apart, twice
        for (_, y), want in zip(pts, means):
            assert v0 + (y - y0) / (y1 - y0) * (v1 - v0) == pytest.approx(want, abs=0.005 * (v1 - v0)), panel[:60]
        knee_x = float(re.search(r'<line x1="([^"]+)"[^>]*class="front"', panel).group(1))
        assert knee_x == pts[1][0]


def test_players_link_their_full_render(site):
    watch = (site / "watch-astronaut-test.html").read_text()
    links = re.findall(r'<a href="([^"]+)" title="the render itself, full size">', watch)
    assert sorted(Path(link).name for link in links) == ["gt.mp4", "lmgs.mp4", "talkinggaussian.mp4"]
    assert all((site / link).resolve().is_file() for link in links)


def test_an_out_folder_that_is_not_a_report_is_never_replaced(site, tmp_path):
    keep = tmp_path / "tables"
    keep.mkdir()
    (keep / "table1_self.md").write_text("mine")
    rc, out, err = run_cli("report", "--results", str(site.parent), "--out", str(keep), "--no-static-charts")
    assert rc == 2 and "--out" in err and "not a report" in err and "Traceback" not in err
    assert [p.name for p in keep.iterdir()] == ["table1_self.md"]
    rc, out, err = run_cli("report", "--results", str(site.parent), "--out", str(tmp_path / "new"), "--preview-side", "8")
    assert rc == 2 and "--preview-side 8" in err and not (tmp_path / "new").exists()
    (tmp_path / "file").write_text("x")
    rc, out, err = run_cli("report", "--results", str(site.parent), "--out", str(tmp_path / "file"))
    assert rc == 2 and "is a file" in err
    # an earlier report is replaced, and the command prints the new index page
    rc, out, err = run_cli("report", "--results", str(site.parent), "--out", str(tmp_path / "site"), "--no-static-charts",
                           "--no-previews")
    assert rc == 0 and out.strip() == str((tmp_path / "site" / "index.html").resolve())
    rc, out, err = run_cli("report", "--results", str(site.parent), "--out", str(tmp_path / "site"), "--no-static-charts",
                           "--no-previews")
    assert rc == 0 and (tmp_path / "site" / "index.html").is_file()


def test_a_render_that_does_not_decode_is_named_on_its_player_and_the_site_is_made(site, tmp_path):
    import shutil

    from lmgs_eval.report.site import build_site

    store = tmp_path / "results"
    shutil.copytree(site.parent, store, ignore=shutil.ignore_patterns("report"))
    (store / "renders" / "talkinggaussian.mp4").write_bytes(b"not a video")
    index, _ = build_site(store, tmp_path / "site", charts=False)
    watch = html.unescape((index.parent / "watch-astronaut-test.html").read_text())
    block = watch.split('data-id="astronaut__self__talkinggaussian--test--seed0')[1].split("</figure>")[0]
    assert "render not readable" in block and "talkinggaussian.mp4" in block and "<video" not in block
    assert watch.count('<video class="main') == 2  # the ground truth and lmgs still play


def test_bad_results_folder_is_one_line_and_writes_nothing(tmp_path):
    rc, out, err = run_cli("report", "--results", str(tmp_path / "nope"), "--out", str(tmp_path / "site"))
    assert rc == 2 and "--results" in err and "not a folder" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "site").exists()
    (tmp_path / "empty").mkdir()
    rc, out, err = run_cli("report", "--results", str(tmp_path / "empty"), "--out", str(tmp_path / "site"))
    assert rc == 2 and "no valid result record" in err and not (tmp_path / "site").exists()


# ----------------------------------------------------------------------------- in Chromium
