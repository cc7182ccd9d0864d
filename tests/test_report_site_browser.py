"""The report site in a headless browser: pages load without console errors, leaderboards sort and filter,
chart hovers name their runs, and the side-by-side players start, seek and play in lockstep."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest

from lmgs.fileio import sha256_file
from lmgs_eval.results import write_record
from test_report_site import FPS, site  # noqa: F401  (site: the report site the static tests check)
from test_results import fixture_records

SHOTS = os.environ.get("LMGS_REPORT_SHOTS")  # also copy the screenshots there (for a note)


def _browser_or_skip():
    from cdp import find_chromium

    binary = find_chromium()
    if binary is None:
        why = "chromium is not installed (apt-get install chromium); the report's browser tests need it"
        if os.environ.get("LMGS_REQUIRE_BROWSER") == "1":  # CI installs it: a missing browser is a failure there
            pytest.fail(why)
        pytest.skip(why)
    pytest.importorskip("websocket", reason="websocket-client (the test extra) drives Chromium")
    return binary


@pytest.fixture(scope="module")
def browser():
    from cdp import Browser

    with Browser(_browser_or_skip()) as b:
        yield b


def _shot(browser, tmp_path: Path, name: str) -> Path:
    import cv2

    look = browser.eval("""(() => { const h = document.querySelector('h1'), r = h.getBoundingClientRect();
        return {bg: getComputedStyle(document.body).backgroundColor, ink: getComputedStyle(h).color,
                box: [r.x + scrollX, r.y + scrollY, r.width, r.height]}; })()""")
    path = browser.screenshot(tmp_path / f"{name}.png")
    if SHOTS:
        browser.screenshot(Path(SHOTS) / f"{name}.png")
    img = cv2.imread(str(path))[..., ::-1].astype(int)
    bg, ink = (np.array([int(c) for c in re.findall(r"\d+", look[k])[:3]]) for k in ("bg", "ink"))
    # the page as drawn: its background colour is the picture's commonest; the heading's text is
    # drawn in the heading's colour inside the heading's box (measured: 0.9-4 % of its pixels)
    colours, counts = np.unique(img.reshape(-1, 3), axis=0, return_counts=True)
    assert np.array_equal(colours[counts.argmax()], bg), (name, colours[counts.argmax()], bg)
    x, y, w, h = (int(round(v)) for v in look["box"])
    heading = img[y:y + h, x:x + w]
    assert (np.abs(heading - ink).sum(-1) <= 24).mean() > 0.003, name
    return path


@pytest.mark.parametrize("page", ["index.html", "board-astronaut.html", "watch-astronaut-test.html", "charts.html",
                                  "run"])
def test_pages_load_without_console_errors(site, browser, page, tmp_path):
    if page == "run":
        page = "runs/" + sorted(p.name for p in (site / "runs").glob("*lmgs--test--seed0*"))[0]
    lmgs = next(r for r in fixture_records() if r["method"]["name"] == "lmgs")
    heading = {"index.html": "Benchmark report", "board-astronaut.html": "Leaderboard: astronaut",
               "watch-astronaut-test.html": "Watch: astronaut (self, test)", "charts.html": "Charts"}.get(
        page, f"Run {lmgs['method']['display_name']} / {lmgs['subject']['name']}")
    browser.open(site / page)
    assert browser.errors() == []
    assert browser.eval("document.querySelector('h1').textContent") == heading
    assert browser.eval("document.title") == f"{heading} · lmgs-eval"
    _shot(browser, tmp_path, "page-" + page.split("/")[0].replace(".html", ""))


def test_leaderboard_sorts_by_any_column_and_filters_by_family(site, browser):
    browser.open(site / "board-astronaut.html")
    table = "document.querySelector('#table1_self-0 table')"
    labels = f"Array.from({table}.tBodies[0].rows).filter(r => !r.hidden).map(r => r.cells[0].dataset.sort)"
    col = browser.eval(f"Array.from({table}.tHead.rows[0].cells).findIndex(th => th.textContent.startsWith('PSNR'))")
    browser.eval(f"{table}.tHead.rows[0].cells[{col}].click()")
    # first click: best first (PSNR is higher-better); the fixture's means: lmgs 38, TalkingGaussian 32, ER-NeRF 27,
    # and the ground truth has no PSNR (identical images): last
    assert browser.eval(labels) == ["Ours (lmgs)", "TalkingGaussian", "ER-NeRF", "Ground Truth"]
    browser.eval(f"{table}.tHead.rows[0].cells[{col}].click()")
    assert browser.eval(labels) == ["ER-NeRF", "TalkingGaussian", "Ours (lmgs)", "Ground Truth"]
    lmd = browser.eval(f"Array.from({table}.tHead.rows[0].cells).findIndex(th => th.textContent.startsWith('LMD'))")
    browser.eval(f"{table}.tHead.rows[0].cells[{lmd}].click()")  # lower-better: smallest first
    assert browser.eval(labels) == ["Ground Truth", "Ours (lmgs)", "TalkingGaussian", "ER-NeRF"]
    browser.eval("document.querySelector('#family-filter input[value=\"NeRF\"]').click()")
    assert "ER-NeRF" not in browser.eval(labels) and "Ours (lmgs)" in browser.eval(labels)


def test_chart_hover_names_the_run_and_config_hash(site, browser):
    browser.open(site / "charts.html")
    assert browser.eval("document.querySelectorAll('svg.chart g.pt').length") >= 3
    text = browser.eval("""(() => { const g = Array.from(document.querySelectorAll('svg.chart g.pt'))
        .find(g => g.textContent.startsWith('Ours')); const r = g.querySelector('circle').getBoundingClientRect();
        g.dispatchEvent(new MouseEvent('mousemove', {bubbles: true, clientX: r.x, clientY: r.y}));
        const c = document.getElementById('hover-card'); return c.hidden ? '' : c.textContent; })()""")
    lmgs = next(r for r in fixture_records() if r["method"]["name"] == "lmgs")
    assert lmgs["config_hash"] in text and "astronaut__self__lmgs--test--seed0" in text


PRESENTED = """(() => { window.__presented = {}; for (const v of document.querySelectorAll('#players video')) {
  const id = v.closest('figure').dataset.id + (v.classList.contains('err') ? ':err' : '');
  const cb = (now, meta) => { window.__presented[id] = meta.mediaTime; v.requestVideoFrameCallback(cb); };
  v.requestVideoFrameCallback(cb); } return true; })()"""


def _frames_now(browser) -> list[int]:
    return browser.eval("lmgsWatch.videos().map(v => Math.floor(v.currentTime * 25 + 1e-3))")


def test_players_start_together_and_stay_within_one_frame_after_a_seek(site, browser, tmp_path):
    browser.open(site / "watch-astronaut-test.html")
    browser.wait_for("lmgsWatch.videos().every(v => v.readyState >= 2)")
    assert browser.eval("lmgsWatch.videos().length") == 5  # 3 players, 2 error maps
    browser.eval(PRESENTED)
    for frame in (12, 3, 17):
        browser.eval(f"lmgsWatch.seekAll({frame})")
        frames = _frames_now(browser)
        assert max(frames) - min(frames) <= 1 and abs(frames[0] - frame) <= 1, frames
        # the frame each player presents (requestVideoFrameCallback), not only its clock
        browser.wait_for("Object.keys(window.__presented).length === 5 && Object.values(window.__presented)"
                         f".every(t => Math.abs(t * 25 - {frame}) < 1.5)", timeout=10)
        assert browser.eval("document.getElementById('cursor').dataset.frame") == str(frame)
        assert browser.eval("document.getElementById('frame-no').textContent").startswith(f"frame {frame} ")
    _shot(browser, tmp_path, "watch-seeked")


LONG = 100  # frames (4 s): long enough to see the players converge and stay together while playing


@pytest.fixture(scope="module")
def long_site(tmp_path_factory) -> Path:
    """A store of one subject with a 4 s ground truth (with audio) and two methods' renders, per-frame PSNR."""
    from lmgs_eval.data.video import write_video
    from lmgs_eval.report.site import build_site
    from lmgs_eval.results import make_record

    root = tmp_path_factory.mktemp("long") / "results"
    rng = np.random.default_rng(0)
    base = rng.uniform(0.2, 0.8, (1, 48, 48, 3)).astype(np.float32)
    gt = np.repeat(base, LONG, 0)
    for i in range(LONG):
        gt[i, 20:28, (i % 40):(i % 40) + 8] = 1.0  # a square moving a pixel a frame
    t = np.arange(LONG * 640) / 16000
    for name, frames in (("ground-truth", gt), ("a", np.clip(gt + 0.05, 0, 1)), ("b", np.roll(gt, 2, 2))):
        write_video(root / "renders" / f"{name}.mp4", (frames * 255).round().astype(np.uint8), fps=FPS,
                    audio=0.2 * np.sin(2 * np.pi * 220 * t) if name == "ground-truth" else None)
        psnr = [float(-10 * np.log10(max(float(((frames[i] - gt[i]) ** 2).mean()), 1e-10))) for i in range(LONG)]
        entry = {"value": float(np.mean(psnr)), "n_original": LONG, "n_effective": LONG, "higher_is_better": True,
                 "unit": "dB", "backend": "numpy", "backend_version": "1", "weights_sha256": None, "flags": [],
                 "per_item": psnr, "standin": None}
        rec = make_record(
            method={"name": name, "display_name": name, "family": "ground-truth" if name == "ground-truth" else "3DGS",
                    "description": "test", "standins": []},
            subject={"name": "long", "bundled": False, "standin": None, "frames": LONG, "width": 48, "height": 48,
                     "path": None, "sha256": None},
            protocol={"name": "self", "version": "1", "clip": "test", "split": "test", "n_frames": LONG},
            metrics={"psnr": entry}, seed=0, config={"name": name},
            artefacts={"render": {"path": f"renders/{name}.mp4", "sha256": sha256_file(root / "renders" / f"{name}.mp4")}})
        write_record(root, rec)
    index, _ = build_site(root, root.parent / "site", charts=False)
    return index.parent


# Right after each tick of the page's clock (its requestAnimationFrame callback ``tick``), what every
# video shows and plays at, and where the cursor is: the controller's decisions, read in the same frame.
TICK_LOG = """(() => { window.__ticks = []; const raf = window.requestAnimationFrame.bind(window);
  window.requestAnimationFrame = (cb) => raf((ts) => { cb(ts); if (cb.name !== 'tick') return;
    const m = lmgsWatch.master();
    window.__ticks.push({t: m.currentTime, cursor: Number(document.getElementById('cursor').dataset.frame),
      videos: lmgsWatch.videos().map(v => ({clock: v === m, time: v.currentTime, rate: v.playbackRate}))}); });
  return true; })()"""


def test_players_stay_in_lockstep_while_playing_and_the_cursor_follows(long_site, browser, tmp_path):
    """Order and content, never a window of wall-clock time (a busy machine only makes it slower):
    while playing, the cursor is the clock's frame at every tick; a follower pushed 3 frames ahead
    is slowed at the very next tick and caught up, one pushed 10 frames (past the 0.25 s hard
    limit) is moved to just ahead of the clock at the next tick; paused, all show one frame."""
    browser.open(long_site / "watch-long-test.html")
    browser.wait_for("lmgsWatch.videos().every(v => v.readyState >= 2)", timeout=60)
    assert browser.eval("lmgsWatch.videos().length") == 5
    browser.eval(TICK_LOG)
    browser.eval("document.getElementById('play').click()")
    browser.wait_for("lmgsWatch.isPlaying() && lmgsWatch.videos().every(v => !v.paused) && __ticks.length >= 3",
                     timeout=60)
    ahead, far = browser.eval("""(() => { const m = lmgsWatch.master(), f = lmgsWatch.videos().filter(v => v !== m);
        window.__mark = __ticks.length; f[0].currentTime = m.currentTime + 3 / 25; f[1].currentTime = m.currentTime + 10 / 25;
        const all = lmgsWatch.videos(); return [all.indexOf(f[0]), all.indexOf(f[1])]; })()""")
    # the controller catches both up; then the clock goes on for another second of frames
    browser.wait_for("__ticks.length > __mark && (() => { const m = lmgsWatch.master(); return lmgsWatch.videos()"
                     ".every(v => Math.abs(v.currentTime - m.currentTime) <= 1 / 25); })()", timeout=60)
    browser.wait_for(f"lmgsWatch.master().currentTime >= __ticks[__mark].t + {FPS} / {FPS}", timeout=60)
    browser.eval("lmgsWatch.pause()")
    ticks, mark = browser.eval("__ticks"), browser.eval("__mark")
    assert len(ticks) > mark + 10
    clock = [k["t"] for k in ticks]
    assert clock == sorted(clock) and clock[-1] - clock[0] >= 1.0  # the clock only moves forward
    for k in ticks:
        assert abs(k["cursor"] - int(k["t"] * FPS + 1e-3)) <= 1, k  # the cursor is the clock's frame
    first = ticks[mark]["videos"]  # the tick right after the push
    t = ticks[mark]["t"]
    assert first[ahead]["time"] - t > 2 / FPS and first[ahead]["rate"] < 1.0, first[ahead]
    assert first[far]["time"] - t == pytest.approx(0.05, abs=0.02) and first[far]["rate"] == 1.0, first[far]
    for k in ticks[mark:]:  # after the push: a follower behind is sped up, one ahead slowed, none left past the limit
        for v in k["videos"]:
            drift = v["time"] - k["t"]
            assert abs(drift) <= 0.25 + 0.05 + 1e-3, k
            if 0.3 / FPS < abs(drift) and abs(drift - 0.05) > 1e-3:
                assert (v["rate"] - 1.0) * drift < 0, k
    browser.wait_for("lmgsWatch.videos().every(v => v.paused && !v.seeking)", timeout=60)
    frames = _frames_now(browser)
    cursor = int(browser.eval("document.getElementById('cursor').dataset.frame"))
    assert len(set(frames)) == 1 and frames[0] == cursor, (frames, cursor)  # paused: all on the cursor's frame
    _shot(browser, tmp_path, "watch-playing")


def test_frame_steps_error_map_and_worst_frames(site, browser, tmp_path):
    browser.open(site / "watch-astronaut-test.html")
    browser.wait_for("lmgsWatch.videos().every(v => v.readyState >= 2)")
    browser.eval("lmgsWatch.seekAll(5)")
    browser.eval("document.getElementById('fwd').click()")
    browser.wait_for("document.getElementById('seek').value === '6'")
    browser.eval("document.getElementById('back').click(); document.getElementById('back').click()")
    browser.wait_for("document.getElementById('seek').value === '4'")
    browser.eval("document.getElementById('errmap').click()")
    assert browser.eval("Array.from(document.querySelectorAll('video.err')).every(v => !v.hidden)")
    assert browser.eval("Array.from(document.querySelectorAll('figure:not(.gt) video.main')).every(v => v.hidden)")
    # the worst LMD frame of lmgs is one click away, and clicking it moves every player there
    lmgs = next(r for r in fixture_records() if r["method"]["name"] == "lmgs" and r["protocol"]["name"] == "self")
    browser.eval("const s = document.getElementById('metric'); s.value = 'lmd'; s.dispatchEvent(new Event('change'))")
    worst = int(np.argmax(lmgs["metrics"]["lmd"]["per_item"]))
    first = browser.eval("document.querySelector('.worst[data-id^=\"astronaut__self__lmgs--\"] button.jump').dataset.frame")
    assert int(first) == worst
    browser.eval("document.querySelector('.worst[data-id^=\"astronaut__self__lmgs--\"] button.jump').click()")
    browser.wait_for(f"document.getElementById('cursor').dataset.frame === '{worst}'")
    # the readout under the curves gives each method's value at that frame, as the record has it
    readout = browser.eval("document.getElementById('readout').textContent")
    assert readout.startswith(f"frame {worst}, LMD: ") and f"Ours (lmgs) {lmgs['metrics']['lmd']['per_item'][worst]:.2f}" in readout
    frames = _frames_now(browser)
    assert max(frames) - min(frames) <= 1 and abs(frames[0] - worst) <= 1
    _shot(browser, tmp_path, "watch-error-map")
