"""Charts and the ``lmgs-eval table`` command from a hand-written results store: the Pareto front, labels
that do not overlap, render contact sheets, deterministic files."""

from __future__ import annotations

import argparse
from pathlib import Path

from lmgs_eval.report import charts as C
from lmgs_eval.report import tables as T
from test_results import fixture_records, typed, write_store


def test_pareto_front_on_hand_made_points():
    # fps (higher better) vs lpips (lower better)
    xs = [1, 2, 3, 4, 5, 2.5]
    ys = [0.10, 0.05, 0.08, 0.03, 0.20, 0.04]
    # (1,.10) dominated by (2,.05); (3,.08) by (4,.03); (2.5,.04) by (4,.03)
    assert C.pareto_front(xs, ys, x_higher=True, y_higher=False) == [3, 4]
    assert C.pareto_front([1, 2, 3], [1, 2, 3], True, True) == [2]
    assert C.pareto_front([1, 2, 3], [3, 2, 1], True, True) == [0, 1, 2]
    assert C.pareto_front([1, 1], [2, 2], True, True) == [0, 1]  # equal points do not dominate each other


def _run_table(tmp_path, results: Path, **kw) -> int:
    from lmgs_eval.commands import table

    ns = argparse.Namespace(results=results, format="all", out=tmp_path / "tables", ci=False, no_charts=False,
                            records=None)
    for k, v in kw.items():
        setattr(ns, k, v)
    return table.run(ns)


def test_table_command_writes_tables_and_deterministic_charts(tmp_path, capsys):
    write_store(tmp_path / "results")
    assert _run_table(tmp_path, tmp_path / "results") == 0
    out = capsys.readouterr().out
    assert out.startswith("## Table I: self-driven reconstruction")
    files = {p.name: p for p in (tmp_path / "tables").iterdir()}
    for name in ("table1_self.md", "table1_self.tex", "table1_self.csv", "table2_cross.md", "table3_theta.tex",
                 "table4_ablation.csv", "calibration.md", "stability_lse_c.md", "status.md",
                 "speed_lpips.png", "speed_lpips.svg", "speed_lmd.png", "speed_lse_c.svg", "train_psnr.png",
                 "stability_lse_c.png"):
        assert name in files and files[name].stat().st_size > 200, name
    assert files["table1_self.md"].read_text() == T.table_self(typed(fixture_records())).markdown()
    first = {n: p.read_bytes() for n, p in files.items()}
    assert _run_table(tmp_path, tmp_path / "results") == 0
    assert {p.name: p.read_bytes() for p in (tmp_path / "tables").iterdir()} == first  # byte-identical rerun
    assert first["speed_lpips.png"][:8] == b"\x89PNG\r\n\x1a\n"


def test_table_command_on_an_empty_store(tmp_path, capsys):
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "junk.json").write_text("[]")
    assert _run_table(tmp_path, tmp_path / "results") == 2
    err = capsys.readouterr().err
    assert "junk.json: skipped" in err and "no result records in" in err
    assert not (tmp_path / "tables").exists()


def test_chart_labels_of_close_points_do_not_overlap():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.2, 3.8))
    xs, ys = [40.0, 41.0, 42.5, 44.0], [0.0330, 0.0332, 0.0329, 0.0331]
    ax.scatter(xs, ys)
    labels = [ax.annotate(f"Method {k}", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
              for k, (x, y) in enumerate(zip(xs, ys))]
    r = fig.canvas.get_renderer()
    assert any(labels[0].get_window_extent(r).overlaps(b.get_window_extent(r)) for b in labels[1:])  # the problem
    C._declutter(fig, ax, labels)
    texts = [t for t in ax.texts if t.get_text().startswith("Method")]
    assert sorted(t.get_text() for t in texts) == [f"Method {k}" for k in range(4)]
    boxes = [t.get_window_extent(r) for t in texts]
    assert not any(boxes[i].overlaps(boxes[j]) for i in range(4) for j in range(i + 1, 4))
    plt.close(fig)


def test_render_sheet_shows_each_methods_video_and_leaves_out_those_not_here(tmp_path):
    # two methods' self-driven renders written as videos of a known flat colour, one method's
    # render absent (made on another machine): the sheet has their rows, in colour, and no others
    import numpy as np

    from lmgs_eval.data.video import write_video

    recs = [r for r in fixture_records() if r["protocol"]["name"] == "self"]
    colours = {"gt": (0.9, 0.9, 0.9), "lmgs": (0.9, 0.1, 0.1), "talkinggaussian": (0.1, 0.1, 0.9),
               "lmgs-no-se": (0.1, 0.9, 0.1)}  # an ablation variant: a Tables III / IV row, not on the sheet
    for r in recs:
        name = r["method"]["name"]
        if name not in colours or r["seed"] != 0:
            continue
        rel = f"renders/{name}.mp4"
        frames = np.ones((10, 64, 64, 3), np.float32) * np.asarray(colours[name], np.float32)
        write_video(tmp_path / rel, (frames * 255).astype(np.uint8))
        r["artefacts"] = {**(r.get("artefacts") or {}), "render": {"path": rel, "sha256": "0" * 64}}
    (png,) = C.render_sheets(typed(recs), tmp_path, tmp_path / "out")
    assert png.name == "renders_astronaut.png"
    import imageio.v3 as iio

    img = iio.imread(png)[..., :3].astype(int)
    red = (img[..., 0] > 180) & (img[..., 1] < 80) & (img[..., 2] < 80)
    blue = (img[..., 2] > 180) & (img[..., 0] < 80) & (img[..., 1] < 80)
    rows_red, rows_blue = np.flatnonzero(red.any(1)), np.flatnonzero(blue.any(1))
    assert red.sum() > 5 * 64 * 40 and blue.sum() > 5 * 64 * 40  # five frames of each method
    assert rows_red.max() < rows_blue.min()  # "Ours (lmgs)" sorts before "TalkingGaussian" within 3DGS
    green = (img[..., 1] > 180) & (img[..., 0] < 80) & (img[..., 2] < 80)
    assert not green.any()
    n_methods = len({r["method"]["name"] for r in recs})
    assert n_methods > 3  # so some rows are missing: the fixture's other methods have no video here
    assert C.render_sheets(typed([r for r in recs if r["method"]["name"] == "ernerf"]), tmp_path, tmp_path / "none") == []
