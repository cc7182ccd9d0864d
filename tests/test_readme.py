"""README.md's Python examples run as written, the model part with only the core install.

The blocks run in one fresh interpreter, in order, sharing one namespace. The first (the model
library) runs with the ``eval`` extra and the layers above ``lmgs`` unimportable, as after
``pip install .`` without extras; the block list is lifted before the next blocks, which use
the evaluation toolkit.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from test_core_install import NOT_IN_CORE

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"

RUNNER = r"""
import contextlib, io, json, sys
root, blocks_file, blocked = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
sys.path.insert(0, root)
blocks = json.load(open(blocks_file))
ns = {"__name__": "__readme__"}
outputs = []
for k, code in enumerate(blocks):
    if k == 0:
        for name in blocked:
            sys.modules[name] = None
    else:
        for name in blocked:
            if sys.modules.get(name, 0) is None:
                del sys.modules[name]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        exec(compile(code, f"README.md python block {k + 1}", "exec"), ns)
    outputs.append(buf.getvalue())
print(json.dumps(outputs))
"""


def python_blocks(text: str) -> list[str]:
    """The bodies of the ```python fenced blocks of a Markdown text, in order."""
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_python_blocks_are_found():
    blocks = python_blocks("a\n```python\nx = 1\n```\n```sh\nls\n```\n```python\ny = 2\nz = 3\n```\n")
    assert blocks == ["x = 1\n", "y = 2\nz = 3\n"]


def test_readme_examples_run(tmp_path):
    blocks = python_blocks(README.read_text())
    assert len(blocks) >= 2, "README.md should show the model library and the evaluation toolkit"
    assert not re.search(r"^\s*(from|import) (lmgs_eval|baselines)\b", blocks[0], flags=re.M), \
        "the README's first example is the model library alone"
    (tmp_path / "blocks.json").write_text(json.dumps(blocks))
    r = subprocess.run([sys.executable, "-c", RUNNER, str(ROOT), str(tmp_path / "blocks.json"), json.dumps(NOT_IN_CORE)],
                       capture_output=True, text=True, timeout=900, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    model_out, score_out = json.loads(r.stdout.strip().splitlines()[-1])[:2]
    # the printed shapes are the ones the comments in the README promise
    assert "torch.Size([48, 48, 3]) torch.Size([48, 48, 1]) 300" in model_out
    assert "(25, 48, 48, 3)" in model_out
    psnr = float(re.search(r"training PSNR ([\d.]+) dB", model_out).group(1))
    assert psnr > 25  # 100 steps fit the toy clip
    # the score record names every metric it ran, and says why LMD and LSE cannot score a face-less disc
    for name in ("psnr", "ssim", "lpips", "lmd", "lse"):
        assert name in score_out
    assert "unavailable" in score_out and (tmp_path / "pred.mp4").exists()
    # the trained model's render against the toy's ground truth, both through lossy mp4
    assert float(re.search(r"psnr=([\d.]+)", score_out).group(1)) > 25


def test_readme_is_short_and_its_links_resolve():
    text = README.read_text()
    assert len(text.splitlines()) <= 155, "README.md is the front door: keep it near 150 lines, move depth to docs/"
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    assert links, "README.md links to its deeper docs"
    for link in links:
        if "://" not in link:
            assert (ROOT / link).exists(), f"README.md links to {link}, which is not in the repository"


@pytest.mark.parametrize("doc", sorted((ROOT / "docs").glob("*.md")), ids=lambda p: p.name)
def test_docs_links_resolve(doc):
    for link in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", doc.read_text()):
        if "://" not in link:
            assert (doc.parent / link).exists(), f"{doc.name} links to {link}, which is not in the repository"


def _subcommands(parser) -> dict:
    import argparse

    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            return a.choices
    return {}


def test_readme_command_lines_name_real_commands_and_flags():
    """Every ``lmgs-eval COMMAND [TARGET] --flag`` the README shows exists in the CLI as it is."""
    from lmgs_eval.cli import build_parser

    commands = _subcommands(build_parser())
    lines = [ln.split("#", 1)[0] for block in re.findall(r"^```sh\n(.*?)^```", README.read_text(), flags=re.S | re.M)
             for ln in block.splitlines() if ln.startswith("lmgs-eval ")]
    assert len(lines) >= 10
    for line in lines:
        words = line.split()
        name = words[1]
        assert name in commands, f"README.md shows 'lmgs-eval {name}', which the CLI does not have"
        parsers = [commands[name]]
        targets = _subcommands(commands[name])
        if targets:  # bench raster|metrics|model, weights import-syncnet
            parsers = []
            for target in words[2].split("|"):
                assert target in targets, f"README.md shows 'lmgs-eval {name} {target}', which the CLI does not have"
                parsers.append(targets[target])
        for parser in parsers:
            known = {s for a in parser._actions for s in a.option_strings}
            for flag in re.findall(r"(?<![\w-])--[a-z][\w-]*", line):
                assert flag in known, f"README.md shows 'lmgs-eval {name} {flag}', which the CLI does not accept"


def test_the_worked_example_of_adding_a_method_runs_in_the_protocol(tmp_path, monkeypatch):
    """docs/adding-a-method.md's adapter, registered as written, goes through `lmgs-eval self` and gets a record."""
    from conftest import run_cli

    from baselines import protocol
    from lmgs_eval.results import load_records

    monkeypatch.setattr(protocol, "_REGISTRY", dict(protocol._REGISTRY))  # the example's name leaves with the test
    (block,) = python_blocks("\n".join(ln[3:] if ln.startswith("   ") else ln
                                       for ln in (ROOT / "docs" / "adding-a-method.md").read_text().splitlines()) + "\n")
    exec(compile(block, "docs/adding-a-method.md", "exec"), {"__name__": "mean_frame_example"})
    assert "mean-frame" in protocol.list_methods()
    rc, out, err = run_cli("self", "--subject", "astronaut-64px-2s", "--method", "mean-frame", "--results", str(tmp_path),
                           "--no-progress")
    assert rc == 0, err
    (rec,) = [r for r in load_records(tmp_path)[0] if r.method.name == "mean-frame"]
    assert rec.method.family == "2D"
    # the PSNR the record holds is the mean frame's, recomputed from the subject's files with skimage
    from skimage.metrics import peak_signal_noise_ratio

    from lmgs_eval.data.registry import find_subject

    subject = find_subject("astronaut-64px-2s", None, progress=False)
    mean = np.mean([subject.frame(i) for i in subject.train_ids], axis=0).round().astype(np.uint8)
    want = np.mean([peak_signal_noise_ratio(subject.frame(i), mean, data_range=255) for i in subject.test_ids])
    assert rec.metrics["psnr"].value == pytest.approx(want, abs=1e-6)
    assert "Mean frame" in out  # the run's row
