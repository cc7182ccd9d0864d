"""The tables from a hand-written results store: golden files, ranking, flags, footnotes, Tables I-IV,
calibration, stability and status (charts and the ``table`` command: ``test_tables_charts.py``)."""

from __future__ import annotations

import copy
import csv
import io
import os
from pathlib import Path

import pytest

from lmgs_eval.report import charts as C
from lmgs_eval.report import tables as T
from lmgs_eval.results.migrate import lmgs_components
from test_results import fixture_records, items, metric, record, typed

GOLDEN = Path(__file__).parent / "golden"


def _golden(name: str, text: str) -> None:
    path = GOLDEN / name
    if os.environ.get("LMGS_UPDATE_GOLDEN"):
        path.parent.mkdir(exist_ok=True)
        path.write_text(text, encoding="utf-8")
    assert text == path.read_text(encoding="utf-8"), f"{path} differs (LMGS_UPDATE_GOLDEN=1 to rewrite)"


def _row(md: str, label: str) -> list[str]:
    line = next(x for x in md.splitlines() if x.startswith(f"| {label} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_table1_matches_golden_markdown_and_latex():
    t = T.table_self(typed(fixture_records()))
    md, tex = t.markdown(), t.latex()
    _golden("table1_self.md", md)
    _golden("table1_self.tex", tex)
    head = _row(md, "Method")
    assert head[:6] == ["Method", "PSNR↑", "LPIPS↓", "LMD↓", "LSE-D↓", "LSE-C↑"]
    assert head[6:] == ["FPS↑", "Train (min)↓", "Gaussians", "MB↓"]
    gt, ours, tg = _row(md, "Ground Truth"), _row(md, "Ours (lmgs)"), _row(md, "TalkingGaussian")
    assert gt[1] == "N/A" and gt[2] == "0.0000" and gt[6] == "–"  # GT: no PSNR against itself, no cost
    assert ours[1].startswith("**38.") and " ± " in ours[1]  # significant winner: bold, mean ± std over 2 seeds
    assert tg[1].startswith("<u>32.")  # runner-up underlined
    assert "\\textbf{38." in tex and "\\underline{32." in tex and "\\toprule" in tex and "$\\pm$" in tex
    assert tex.index("Ground Truth") < tex.index("ER-NeRF") < tex.index("Ours (lmgs)")


def test_non_significant_difference_is_not_bolded():
    md = T.table_self(typed(fixture_records())).markdown()
    ours, tg = _row(md, "Ours (lmgs)"), _row(md, "TalkingGaussian")
    # LSE-D / LSE-C: Ours is better on the mean, but by far less than the item noise.
    for cell in (ours[4], ours[5], tg[4], tg[5]):
        assert cell.endswith("†") and "**" not in cell and "<u>" not in cell
    assert "† LSE-D: Ours (lmgs), TalkingGaussian (Welch t on seed means, 2 vs 2 seeds, p = " in md
    assert "no winner is bolded" in md
    tex = T.table_self(typed(fixture_records())).latex()
    assert "$^\\dagger$" in tex


def test_mixed_backends_are_flagged_and_not_ranked():
    recs = fixture_records()
    for r in recs:
        if r["method"]["name"] == "ernerf" and r["protocol"]["name"] == "self":
            r["metrics"]["lpips"]["backend"] = "lpips-alex"
    t = T.table_self(typed(recs))
    md, tex = t.markdown(), t.latex()
    assert "LPIPS↓ ‡" in _row(md, "Method")
    lp = [_row(md, name)[2] for name in ("ER-NeRF", "TalkingGaussian", "Ours (lmgs)")]
    assert all(c.endswith("‡") and "**" not in c and "<u>" not in c for c in lp)
    assert "‡ LPIPS mixes metric backends (ER-NeRF: lpips-alex v1; " in md
    assert "LPIPS made by lpips-alex v1, stlpips-alex v1" in md
    assert "\\textbf{LPIPS}$\\downarrow$$^\\ddagger$" in tex
    # the other columns are still ranked
    assert _row(md, "Ours (lmgs)")[1].startswith("**")


def test_a_custom_alexnet_trunk_has_its_own_column_never_the_lpips_one():
    recs = fixture_records()
    custom = "an AlexNet-shaped trunk that is not torchvision's published alexnet-owt-7be5be79.pth"
    for r in recs:
        if r["method"]["name"] == "ernerf" and r["protocol"]["name"] == "self":
            e = r["metrics"].pop("lpips")
            r["metrics"]["lpips_custom"] = {**e, "backend": "lpips-alex-custom(1234abcd)", "backend_version": "0.1",
                                            "standin": custom}
    md = T.table_self(typed(recs)).markdown()
    assert _row(md, "Method")[1:5] == ["PSNR↑", "LPIPS↓", "LPIPS (custom trunk)↓", "LMD↓"]
    er, ours, tg = _row(md, "ER-NeRF"), _row(md, "Ours (lmgs)"), _row(md, "TalkingGaussian")
    assert er[2] == "N/A" and er[3].startswith("0.086")  # the custom number is not in the LPIPS column
    assert ours[3] == tg[3] == "N/A"
    assert "‡" not in md and ours[2].startswith("**0.0128")  # the LPIPS column is still one backend, ranked
    assert f"LPIPS (custom trunk) made by lpips-alex-custom(1234abcd) v0.1; STAND-IN: {custom}." in md
    assert "LPIPS made by stlpips-alex v1;" in md
    assert "custom trunk" not in T.table_self(typed(fixture_records())).markdown()  # shown only when a record has one


def test_fps_timed_on_a_busy_host_is_marked():
    recs = fixture_records()
    quiet = T.table_self(typed(recs)).markdown()
    assert "§" not in quiet
    for r in recs:
        if r["protocol"]["name"] == "self":
            r["cost"]["others_cpu_share"] = 0.02
            if r["method"]["name"] == "ernerf" and r["seed"] == 1:
                r["cost"]["others_cpu_share"] = 0.47  # another process had about one of two cores
    md = T.table_self(typed(recs)).markdown()
    fps = _row(md, "Method").index("FPS↑")
    assert _row(md, "ER-NeRF")[fps].endswith("§")
    assert not _row(md, "Ours (lmgs)")[fps].endswith("§") and not _row(md, "TalkingGaussian")[fps].endswith("§")
    assert "§ FPS timed on a busy or slowed host: other processes took more than 10% of its CPU" in md
    assert "ER-NeRF 1/2 runs, worst others 47%" in md
    # the metric columns are ranked as before: the mark only concerns the timing
    assert [_row(md, n)[1] for n in ("Ours (lmgs)", "TalkingGaussian")] == \
        [_row(quiet, n)[1] for n in ("Ours (lmgs)", "TalkingGaussian")]


def test_fps_timed_on_a_slowed_host_is_marked():
    # the guest saw no other process, but the host ran the fixed probe 2.3x slower than its best
    recs = fixture_records()
    for r in recs:
        if r["protocol"]["name"] == "self":
            r["cost"].update(others_cpu_share=0.03, host_slowdown=1.1)
            if r["method"]["name"] == "talkinggaussian":
                r["cost"]["host_slowdown"] = 2.3
    md = T.table_self(typed(recs)).markdown()
    fps = _row(md, "Method").index("FPS↑")
    assert _row(md, "TalkingGaussian")[fps].endswith("§") and not _row(md, "Ours (lmgs)")[fps].endswith("§")
    assert "TalkingGaussian 2/2 runs, worst probe 2.3x slower" in md  # two seeds in the fixture
    assert "slower than its best on that machine (cost.host_slowdown)" in md


def test_training_time_measured_on_a_busy_host_is_marked():
    recs = fixture_records()
    for r in recs:
        if r["protocol"]["name"] == "self":
            r["cost"]["train_others_cpu_share"] = 0.04
            if r["method"]["name"] == "lmgs" and r["seed"] == 0:
                r["cost"]["train_others_cpu_share"] = 0.52
    md = T.table_self(typed(recs)).markdown()
    head = _row(md, "Method")
    train, fps = head.index("Train (min)↓"), head.index("FPS↑")
    assert _row(md, "Ours (lmgs)")[train].endswith("§") and not _row(md, "TalkingGaussian")[train].endswith("§")
    assert not _row(md, "Ours (lmgs)")[fps].endswith("§")  # the render timing was not busy
    assert "§ Train: trained while other processes took more than 10% of the host's CPU" in md
    assert "Ours (lmgs) 1/2 runs, worst others 52%" in md


def test_ranking_without_per_item_values_says_it_is_untested():
    # One seed each and no per-frame values: neither a seed-level nor a frame-level test is possible.
    recs = [r for r in fixture_records() if r["seed"] == min(x["seed"] for x in fixture_records())]
    for r in recs:
        for m in r["metrics"].values():
            m["per_item"] = None
    md = T.table_self(typed(recs)).markdown()
    assert _row(md, "Ours (lmgs)")[4].startswith("**")
    assert "LSE-D: best / second not tested for significance" in md


def test_marks_name_their_test_seeds_when_both_rows_have_seeds_else_frames():
    recs = fixture_records()
    md = T.table_self(typed(recs)).markdown()
    # both rows have two seeds: the seed-level test made the bold PSNR
    assert "PSNR Ours (lmgs) vs TalkingGaussian: Welch t on seed means, 2 vs 2 seeds" in md
    one = [r for r in recs if not (r["method"]["name"] == "talkinggaussian" and r["seed"] != min(
        x["seed"] for x in recs))]
    md1 = T.table_self(typed(one)).markdown()
    assert "PSNR Ours (lmgs) vs TalkingGaussian: circular block bootstrap over" in md1


def test_footnotes_name_standins_backends_and_descriptions():
    md = T.table_self(typed(fixture_records())).markdown()
    assert "LPIPS made by stlpips-alex v1; STAND-IN: ST-LPIPS" in md
    assert "LSE-D made by onnxruntime:bundled-sync v1; STAND-IN: bundled sync scorer" in md
    assert "Subject astronaut: bundled, synthetic: synthetic head" in md
    assert "- Ours (lmgs) (3DGS): Ours (lmgs): reimplemented on the shared renderer" in md
    assert "Cost measured on Test CPU, 2 threads, no GPU." in md


def test_a_subject_own_gaussian_budget_is_named_with_the_rows_that_used_it():
    from lmgs_eval.results import BUDGET_NOTE, budget_note

    recs = fixture_records()
    note = budget_note(0.55, 0.3)
    assert note.startswith(f"{BUDGET_NOTE}0.55 per pixel of face area, this subject's capacity knee")
    for r in recs:
        if r["method"]["name"] in ("lmgs", "talkinggaussian"):
            r["run"] = {"budget": {"density": 0.55, "preset_density": 0.3}}
    other = copy.deepcopy([r for r in recs if r["method"]["name"] == "lmgs" and r["protocol"]["name"] == "self"])
    for r in other:  # another subject, at the preset's budget: nothing to say
        r["subject"] = dict(r["subject"], name="may", bundled=False, standin=None)
        r.pop("run")
    md = T.table_self(typed(recs + other)).markdown()
    assert f"- Subject astronaut: {note} (Ours (lmgs), TalkingGaussian)." in md
    assert md.count(BUDGET_NOTE) == 1
    assert BUDGET_NOTE not in T.table_self(typed(fixture_records())).markdown()


def test_the_plate_reference_row_sits_under_the_ground_truth_unranked():
    from test_results import N_ITEMS, metric

    ref = record("plate-reference", "GT head on plate", "reference", 0, {
        "psnr": metric("psnr", items(24.8, 0.5, 950)), "lpips": metric("lpips", [0.001] * N_ITEMS),
        "lmd": metric("lmd", [0.0] * N_ITEMS)}, description="the frames' head composited on the plate", cost={"fps": 999.0})
    recs = fixture_records() + [ref]
    md = T.table_self(typed(recs)).markdown()
    labels = [line.split("|")[1].strip() for line in md.splitlines() if line.startswith("| ") and "---" not in line]
    assert labels[1:3] == ["Ground Truth", "GT head on plate"] and labels[-1] == "Ours (lmgs)"
    row = _row(md, "GT head on plate")
    assert row[1] == "24.80" and row[2] == "0.0010" and row[6] == "–"  # unranked (its LPIPS beats all), no cost
    assert _row(md, "Ours (lmgs)")[2].startswith("**")  # the best method is still bolded
    assert "GT head on plate (reference): the frames' head composited on the plate" in md
    assert "GT head on plate" not in T.table_calibration(typed(recs)).markdown()
    assert not any(p["label"] == "GT head on plate" for p in C._points(typed(recs), "fps", "psnr"))


def test_per_subject_sections():
    recs = fixture_records()
    other = []
    for r in recs:
        if r["protocol"]["name"] == "self" and r["method"]["name"] in ("gt", "lmgs"):
            r2 = copy.deepcopy(r)
            r2["subject"] = dict(r2["subject"], name="may", bundled=False, standin=None)
            other.append(r2)
    t = T.table_self(typed(recs + other))
    assert [s.title for s in t.sections] == ["astronaut (bundled)", "may"]
    tex = t.latex()
    assert "\\multicolumn{10}{l}{\\textit{may}}" in tex


def test_table2_cross_layout():
    t = T.table_cross(typed(fixture_records()))
    md, tex = t.markdown(), t.latex()
    assert _row(md, "Method") == ["Method", "Audio A LSE-D↓", "Audio A LSE-C↑", "Audio B LSE-D↓", "Audio B LSE-C↑"]
    assert _row(md, "Ours (lmgs)")[1] == "**9.000**"
    assert "\\multicolumn{2}{c}{Audio A} & \\multicolumn{2}{c}{Audio B}" in tex
    assert "\\cmidrule(lr){2-3} \\cmidrule(lr){4-5}" in tex


def declared(recs: list[dict]) -> list[dict]:
    """Copies of hand-written records with the components the lmgs adapter declares for their configs
    (the tests below state a variant by editing its config, as a version-1 record did)."""
    out = copy.deepcopy(recs)
    for r in out:
        name = r["method"]["name"]
        if (name == "lmgs" or name.startswith("lmgs-")) and "guidance" in r["config"]:
            r["method"]["components"] = lmgs_components(r["config"])
    return out


def table_ablation(recs):
    return T.table_ablation(typed(declared(recs)))


def table_theta(recs):
    return T.table_theta(typed(declared(recs)))


def test_table3_theta_and_table4_ablation():
    recs = fixture_records()
    md3 = table_theta(recs).markdown()
    labels = [ln.split("|")[1].strip() for ln in md3.splitlines() if ln.startswith("| 0.")]
    assert labels == ["0.4", "0.6", "0.8"]
    assert _row(md3, "θ")[1] == "Points enhanced" and _row(md3, "0.6")[1] == "–"  # no note, no number
    assert _row(md3, "0.6")[2].startswith("**")
    # The share of points SE selected comes from the record's run.se_fraction, averaged over seeds.
    from lmgs_eval.results import se_fraction

    noted = copy.deepcopy(recs)
    for r in noted:
        if r["method"]["name"] == "lmgs" and r["protocol"]["name"] == "self":
            r["run"] = {"se_fraction": (70.0 + 2 * r["seed"]) / 100}
    assert se_fraction(typed([dict(recs[0], run={"se_fraction": 0.733})])[0]) == pytest.approx(0.733)
    assert se_fraction(typed(recs)[0]) is None
    assert _row(table_theta(noted).markdown(), "0.6")[1] == "71.0% (70.0-72.0)"  # seeds 0 and 1: mean (range)
    md4 = table_ablation(recs).markdown()
    order = [ln.split("|")[1].strip() for ln in md4.splitlines() if ln.startswith("| w/o") or ln.startswith("| Full")]
    assert order == ["w/o SE", "w/o LC", "w/o GR", "Full model"]
    assert _row(md4, "w/o SE")[1:4] == ["✗", "✓", "✓"] and _row(md4, "Full model")[1:4] == ["✓", "✓", "✓"]
    tex4 = table_ablation(recs).latex()
    assert "$\\times$ & \\checkmark" in tex4
    # A baseline on the same backbone (config keys alike, SE/LC off, GR on) is another method,
    # not the "w/o SE, LC" ablation row, and it must not be merged into a variant's row either.
    degs = copy.deepcopy(next(r for r in recs if r["method"]["name"] == "lmgs-no-se"))
    degs["method"].update(name="degstalk", display_name="DEGSTalk", variant=None)
    degs["config"] = {"guidance": {"se": False, "lc": False, "theta": 0.6}, "gr": True}
    md4b = table_ablation(recs + [degs]).markdown()
    assert md4b == md4 and "w/o SE, LC" not in md4b
    assert table_theta(recs + [degs]).markdown() == md3


def test_table4_has_the_papers_audio_rows_first():
    """The paper's Table IV starts with "Replacing Audio Net with DS" and "w/o Audio Encoder"."""
    recs = copy.deepcopy(fixture_records())
    for r in recs:
        if r["method"]["name"].startswith("lmgs"):
            r["config"]["audio"] = {"frontend": "logmel", "use_encoder": True}
    base = next(r for r in recs if r["method"]["name"] == "lmgs-no-gr")
    for name, audio in (("lmgs-ds", {"frontend": "ds", "use_encoder": True}),
                        ("lmgs-no-ae", {"frontend": "logmel", "use_encoder": False})):
        r = copy.deepcopy(base)
        r["method"].update(name=name, display_name=name, variant=name.removeprefix("lmgs-"))
        r["config"] = {**r["config"], "gr": True, "audio": audio}
        recs.append(r)
    md4 = table_ablation(recs).markdown()
    order = [ln.split("|")[1].strip() for ln in md4.splitlines()
             if ln.startswith(("| w/o", "| Full", "| Replacing"))]
    assert order == ["Replacing Audio Net with DS", "w/o Audio Encoder", "w/o SE", "w/o LC", "w/o GR", "Full model"]
    assert _row(md4, "w/o Audio Encoder")[1:4] == ["✓", "✓", "✓"]
    # An added GR weighting (not in the paper) gets its own row after the paper's, GR ticked.
    r = copy.deepcopy(base)
    r["method"].update(name="lmgs-gr-mean", display_name="lmgs-gr-mean", variant="gr-mean")
    r["config"] = {**r["config"], "gr": True, "audio": {"frontend": "logmel", "use_encoder": True},
                   "train": {"normal_reduce": "mean", "lambda_normal": 0.05}}
    md4 = table_ablation(recs + [r]).markdown()
    label = "GR, normal term per pixel (mean, λ_N = 0.05)"
    assert _row(md4, label)[1:4] == ["✓", "✓", "✓"]
    rows = [ln.split("|")[1].strip() for ln in md4.splitlines() if ln.startswith("| ")]
    assert rows.index("w/o GR") < rows.index(label) < rows.index("Full model")
    # The row names the GR form that differs from the full model's: with a per-pixel full model,
    # the paper's summed form is the added row, and the per-pixel records are the full model's.
    per_pixel = copy.deepcopy(recs)
    for x in per_pixel:
        if x["method"]["name"].startswith("lmgs") and x["config"].get("gr", True):
            x["config"]["train"] = {"normal_reduce": "mean", "lambda_normal": 0.05}
    paper = copy.deepcopy(r)
    paper["method"].update(name="lmgs-gr-paper", display_name="lmgs-gr-paper", variant="gr-paper")
    paper["config"] = {**paper["config"], "train": {}}
    md4c = table_ablation(per_pixel + [paper]).markdown()
    summed = "GR as the paper writes it (normal term summed, λ_N = 0.0001)"
    assert _row(md4c, summed)[1:4] == ["✓", "✓", "✓"] and label not in md4c
    rows = [ln.split("|")[1].strip() for ln in md4c.splitlines() if ln.startswith("| ")]
    assert rows.index("w/o GR") < rows.index(summed) < rows.index("Full model")
    # Neither audio row is a θ row of Table III.
    assert table_theta(recs).markdown() == table_theta(fixture_records()).markdown()
    # Training on out-of-fold landmarks (lmgs-oof) is its own row, SE / LC / GR ticked, not a θ row.
    oof = copy.deepcopy(next(x for x in recs if x["method"]["name"] == "lmgs"))
    oof["method"].update(name="lmgs-oof", display_name="lmgs-oof", variant="oof")
    oof["config"] = {**oof["config"], "train": {**(oof["config"].get("train") or {}), "landmark_folds": 5}}
    md4d = table_ablation(recs + [oof]).markdown()
    assert _row(md4d, "Training landmarks out of fold (5 folds)")[1:4] == ["✓", "✓", "✓"]
    assert table_theta(recs + [oof]).markdown() == table_theta(recs).markdown()
    # lmgs with the mouth state and the generic lip model's tuned mouth (dotted --set keys, the method's name
    # unchanged) is not called the full model: its row names both, beside the folds
    mouth = copy.deepcopy(oof)
    mouth["method"].update(name="lmgs", display_name="Ours (lmgs, generic mouth, tuned, mouth state)", variant=None)
    mouth["config"] = {**mouth["config"], "guidance": {**mouth["config"]["guidance"], "mouth_state": True},
                       "train": {**mouth["config"]["train"], "landmark_source": "generic-tuned"}}
    mouth["config_hash"] = "f" * 16
    md4m = table_ablation(recs + [mouth]).markdown()
    both = ("Mouth state read by the deformations, Mouth from the generic lip model, fine-tuned on the subject, "
            "Training landmarks out of fold (5 folds)")
    assert _row(md4m, both + " [ffffffff]")[1:4] == ["✓", "✓", "✓"]  # two configs of `lmgs`: each row says its hash
    rows = [ln.split("|")[1].strip() for ln in md4m.splitlines() if ln.startswith("| ")]
    assert rows[-1].startswith("Full model [") and rows.index(both + " [ffffffff]") < len(rows) - 1  # the full model last
    # SE capped at a share of the points, against a full model by θ alone, likewise
    cap20 = copy.deepcopy(next(x for x in recs if x["method"]["name"] == "lmgs"))
    cap20["method"].update(name="lmgs-cap20", display_name="lmgs-cap20", variant="cap20")
    cap20["config"] = {**cap20["config"], "guidance": {**cap20["config"]["guidance"], "select_fraction": 0.2}}
    md4e = table_ablation(recs + [cap20]).markdown()
    assert _row(md4e, "SE capped at 20% of the points")[1:4] == ["✓", "✓", "✓"]
    assert table_theta(recs + [cap20]).markdown() == table_theta(recs).markdown()
    # the label says how a row's SE differs from the full model's: with the full model capped (lmgs's
    # default), the row by θ alone is the variant, and a record made before the option counts as uncapped
    capped = [copy.deepcopy(x) for x in recs]
    for x in capped:
        if x["method"]["name"] == "lmgs":
            x["config"] = {**x["config"], "guidance": {**x["config"].get("guidance", {}), "select_fraction": 0.2}}
    uncapped = copy.deepcopy(next(x for x in recs if x["method"]["name"] == "lmgs"))
    uncapped["method"].update(name="lmgs-uncapped", display_name="lmgs-uncapped", variant="uncapped")
    md4f = table_ablation(capped + [uncapped]).markdown()
    assert _row(md4f, "SE by θ alone (uncapped)")[1:4] == ["✓", "✓", "✓"] and "SE capped" not in md4f
    assert _row(md4f, "Full model")[1:4] == ["✓", "✓", "✓"]

def _calibration_store(constant: bool) -> list[dict]:
    lse_c_gt = [5.0] * 20 if constant else items(8.5, 0.4, 1)
    recs = [record("gt", "Ground Truth", "ground-truth", 0, {
        "lse_c": metric("lse_c", lse_c_gt), "lmd": metric("lmd", [0.0] * 20)})]
    recs.append(record("gt-shift+10", "GT, audio +10", "control", 0, {"lse_c": metric("lse_c", [5.0] * 20)},
                       control={"kind": "audio-shift", "targets": ["lse_c"]}))
    recs.append(record("still-frame", "Still frame", "control", 0, {
        "lse_c": metric("lse_c", [5.0] * 20), "lmd": metric("lmd", items(3.0, 0.2, 2))},
        control={"kind": "still-frame", "targets": ["lmd", "lse_c"]}))
    return recs


def test_calibration_flags_a_metric_that_does_not_separate():
    md = T.table_calibration(typed(_calibration_store(constant=True)), metrics=("lmd", "lse_c")).markdown()
    verdict = _row(md, "GT separated from its controls")
    assert verdict[1:] == ["✓", "✗"]
    assert _row(md, "Still frame")[2].endswith("✗") and not _row(md, "Still frame")[1].endswith("✗")
    assert "✗ LSE-C does not separate the ground truth from: GT, audio +10, Still frame" in md
    good = T.table_calibration(typed(_calibration_store(constant=False)), metrics=("lmd", "lse_c")).markdown()
    assert _row(good, "GT separated from its controls")[1:] == ["✓", "✓"]
    # the fixture store: GT separates on every metric its controls target
    md = T.table_calibration(typed(fixture_records())).markdown()
    assert _row(md, "GT separated from its controls")[1:] == ["–", "–", "✓", "✓", "✓", "–"]  # no av_offset in the fixture


def test_stability_and_status_tables():
    recs = fixture_records()
    md = T.table_stability(typed(recs), "lse_c").markdown()
    assert _row(md, "Method") == ["Method", "long-300s", "noise-10db", "silence", "failed runs", "suite wall (min)"]
    tg = _row(md, "TalkingGaussian")
    assert tg[1] == "1 failed: out of memory" and tg[4] == "1"
    assert tg[2].startswith("-0.8") and tg[3].startswith("-4.0")
    # a metric only the silence condition has (mouth opening): its value itself, said so; no clean run at all: said so
    sil = next(r for r in recs if r["method"]["name"] == "talkinggaussian" and r["protocol"]["clip"] == "silence")
    sil["metrics"]["silence_open"] = dict(sil["metrics"]["lse_c"], value=2.5, per_item=None, higher_is_better=False)
    md = T.table_stability(typed(recs), "silence_open").markdown()
    assert _row(md, "TalkingGaussian")[3].startswith("2.5") and "silence: " in md and "not measured on the clean clip" in md
    no_clean = [r for r in copy.deepcopy(recs) if not (r["protocol"]["name"] == "stress" and r["protocol"]["clip"] == "clean")]
    assert _row(T.table_stability(typed(no_clean), "silence_open").markdown(), "TalkingGaussian")[3] == "no clean run"
    st = T.table_status(typed(recs)).markdown()
    assert _row(st, "TalkingGaussian")[1] == "7 ok, 1 failed: out of memory (stress:long-300s); paper's order 10/10"
    assert _row(st, "ER-NeRF")[1] == "ok (4); paper's order 10/10"


def test_csv_is_machine_readable_with_cis():
    rows = list(csv.DictReader(io.StringIO(T.table_self(typed(fixture_records())).csv())))
    ours = next(r for r in rows if r["method"] == "lmgs")
    assert float(ours["psnr_ci_lo"]) < float(ours["psnr"]) < float(ours["psnr_ci_hi"])
    assert ours["psnr_n_seeds"] == "2" and ours["psnr_mark"] == "best" and ours["lse_d_mark"] == "tie"
    assert ours["lpips_backend"] == "stlpips-alex v1"
    assert "[" in T.table_self(typed(fixture_records())).markdown(show_ci=True)


def test_status_counts_pairs_ordered_as_in_the_papers_table_i():
    # paper: lmgs > talkinggaussian > ernerf on PSNR; LPIPS/LMD lower is better in the same order
    m = lambda k, v: metric(k, None, value=v)  # noqa: E731
    recs = [record("lmgs", "Ours", "3DGS", 0, {"psnr": m("psnr", 30.0), "lpips": m("lpips", 0.05), "lmd": m("lmd", 1.0)}),
            record("talkinggaussian", "TG", "3DGS", 0, {"psnr": m("psnr", 31.0), "lpips": m("lpips", 0.06), "lmd": m("lmd", 1.1)}),
            record("ernerf", "ER", "NeRF", 0, {"psnr": m("psnr", 25.0), "lpips": m("lpips", 0.10), "lmd": m("lmd", 2.0)}),
            record("lmgs", "Ours", "3DGS", 0, {"psnr": m("psnr", 99.0)}, variant="no-se"),  # variants do not count
            record("mymethod", "Mine", "3DGS", 0, {"psnr": m("psnr", 40.0)})]  # not in the paper
    # lmgs vs TG: PSNR disagrees, LPIPS and LMD agree; lmgs vs ER: all three agree -> 5 of 6
    assert T.paper_order_agreement(typed(recs), "lmgs", "astronaut") == (5, 6)
    # ER-NeRF is behind both in the paper and here on all three metrics
    assert T.paper_order_agreement(typed(recs), "ernerf", "astronaut") == (6, 6)
    assert T.paper_order_agreement(typed(recs), "mymethod", "astronaut") is None
    md = T.table_status(typed(recs)).markdown()
    assert "paper's order 5/6" in _row(md, "Ours")[1]
    assert "paper's order" not in _row(md, "Mine")[1]


def test_an_lse_that_failed_its_self_check_is_marked_and_never_ranked():
    """Table I: lmgs is the best on LSE-D and LSE-C in the fixture; when its scorer's self-check failed on
    its clips, its figures stay (marked ¶) and the ranking goes to the methods whose LSE can be trusted."""
    recs = copy.deepcopy(fixture_records())
    md = T.table_self(typed(recs)).markdown()
    assert "¶" not in md
    for r in recs:
        if r["method"]["name"] == "lmgs" and r["protocol"]["name"] == "self":
            r["metrics"]["lse_d"]["values"] = {"trusted": False, "separation": 0.4}
    md = T.table_self(typed(recs)).markdown()
    row = _row(md, "Ours (lmgs)")
    assert row[4].endswith("¶") and row[5].endswith("¶") and "**" not in row[4] + row[5]
    assert row[1].startswith("**")  # PSNR is not an LSE figure: still ranked
    assert "¶ LSE-D: the sync scorer did not pass its self-check on Ours (lmgs)" in md
    assert "lmgs-eval weights import-syncnet" in md
    assert any(_row(md, name)[4].startswith(("**", "<u>")) for name in ("TalkingGaussian", "ER-NeRF"))
