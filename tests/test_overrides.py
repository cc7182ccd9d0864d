"""One override path for every method: ``--set KEY=VALUE`` checked against the config's field types,
presets a method lacks and devices a machine lacks refused in one line before any work."""

from __future__ import annotations

import pytest
import torch
from conftest import run_cli

from lmgs.config import config_hash, override
from lmgs.errors import InputError
from lmgs.presets import quick

SUBJECT = "astronaut-64px-2s"


def test_override_sets_nested_fields_with_their_types():
    cfg = override(quick(), {"train.dynamic_steps": 40, "guidance.theta": 1, "gr": False,
                             "audio.encoder_channels": [16, 16, 32, 32]})
    assert cfg.train.dynamic_steps == 40 and cfg.gr is False
    assert cfg.guidance.theta == 1.0 and isinstance(cfg.guidance.theta, float)  # an integer is a number
    assert cfg.audio.encoder_channels == (16, 16, 32, 32)  # a JSON list is the tuple the field holds
    assert quick().train.dynamic_steps != 40  # the preset itself is untouched (frozen)


@pytest.mark.parametrize("changes, words", [
    ({"train.dynamic_steps": "abc"}, "--set train.dynamic_steps='abc': expected an integer, got str"),
    ({"train.dynamic_steps": 4.5}, "expected an integer, got float"),
    ({"gr": "yes"}, "--set gr='yes': expected true or false, got str"),
    ({"audio.frontend": "wav2vec"}, "expected 'logmel' or 'mfcc' or 'ds' or 'hu' or 'wavlm'"),
    ({"audio.encoder_channels": [16, 16]}, "expected a list of 4 integers, got list"),
    ({"train.nope": 1}, "--set train.nope: TrainConfig has no field 'nope'; its fields: budget_density"),
    ({"train": 3}, "'train' is a section; set one of its fields"),
    ({"gr.x": 3}, "'gr' is a value, not a section"),
])
def test_a_bad_override_is_one_line_naming_the_key(changes, words):
    with pytest.raises(InputError) as e:
        override(quick(), changes)
    assert words in str(e.value) and "\n" not in str(e.value)


def test_one_hasher_for_every_config():
    """lmgs's hash is the toolkit's hash of its config dict, whatever the key order."""
    cfg = quick()
    assert cfg.hash() == config_hash(cfg.to_dict()) == config_hash(dict(reversed(list(cfg.to_dict().items()))))
    assert config_hash({"a": 1}) != config_hash({"a": 2})


@pytest.mark.parametrize("args, words", [
    (["--set", "train.dynamic_steps=abc"], "error: --set train.dynamic_steps='abc': expected an integer, got str"),
    (["--method", "talkinggaussian", "--set", "train.bogus=1"], "error: method 'talkinggaussian' has no setting 'bogus'"),
    (["--method", "wav2lip", "--set", "steps=fast"], "expected an integer, got str"),
    (["--method", "talkinggaussian", "--preset", "paper"], "error: --preset paper: method 'talkinggaussian' has no such"),
    (["--device", "banana"], "error: --device 'banana': not a device (cpu, cuda, cuda:N)"),
])
def test_bad_options_stop_the_run_before_any_work(tmp_path, args, words):
    rc, out, err = run_cli("self", "--subject", SUBJECT, "--results", str(tmp_path / "res"), "--no-progress", *args)
    assert rc == 2 and words in err and "Traceback" not in err
    assert [ln for ln in err.splitlines() if "error" in ln] == [next(ln for ln in err.splitlines() if words in ln)]
    assert not (tmp_path / "res").exists()  # nothing scored, nothing written


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA: asking for it is not an error here")
def test_asking_for_cuda_on_a_machine_without_it_is_refused(tmp_path):
    rc, _, err = run_cli("self", "--subject", SUBJECT, "--results", str(tmp_path), "--device", "cuda")
    assert rc == 2 and "--device 'cuda': CUDA is not available on this machine" in err
