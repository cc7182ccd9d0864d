"""The lip model's weights files: the shipped ones (their sha256 recorded here and checked on load), files made
elsewhere by ``scripts/train_lip_model.py``, and each file's provenance: which real recordings it was adapted on
and which clips it holds out (a clip it was adapted on is not a held-out test for it)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from lmgs.errors import InputError

FOLDER = Path(__file__).with_name("lips_models")
# file -> (what it is, sha256); written by scripts/train_lip_model.py
WEIGHTS = {
    "lips_generated.pt": ("the lip model pretrained on the bundled generator's clips",
                          "d678bdec71957153c94da1304a40bf9319806d0d7fd42948dd1648963bd68a2d"),
    "lips_generic.pt": ("the lip model adapted on real speakers' lip tracks",
                        "edaa71ed0db72f39a033f3070ae66993d150d581106fc1c430a9955d29740425"),
}
DEFAULT = "lips_generic.pt"
# Which real recordings each shipped file was adapted on (clip name, the video file's sha256, frames), written by
# scripts/train_lip_model.py beside the weights; a weights file elsewhere carries the same as ``<file>.json``.
PROVENANCE = "provenance.json"


def weights_file(name_or_path: str | Path, *, check: bool = True) -> Path:
    """The file of a lip model: a shipped one (a key of :data:`WEIGHTS`; missing or, with ``check``, altered: one
    line) or a path that exists."""
    from lmgs.fileio import sha256_file

    name = str(name_or_path)
    if name in WEIGHTS:
        what, sha = WEIGHTS[name]
        p = FOLDER / name
        if not p.is_file():
            raise InputError(f"{p}: {what} is missing (reinstall lmgs)")
        if check:
            got = sha256_file(p)
            if got != sha:
                raise InputError(f"{p}: {what} is altered (sha256 {got[:12]}..., expected {sha[:12]}...)")
        return p
    p = Path(name_or_path)
    if not p.is_file():
        raise InputError(f"{p}: no such lip model file")
    return p


def weights_sha256(name_or_path: str | Path) -> str:
    """The sha256 of a lip model's weights: the recorded one for a shipped name, the file's own for a path."""
    from lmgs.fileio import sha256_file

    if str(name_or_path) in WEIGHTS:
        return WEIGHTS[str(name_or_path)][1]
    return sha256_file(weights_file(name_or_path))


def check_weights(name_or_path: str | Path) -> None:
    """A lip model name lmgs can load: a shipped name, or a file that exists (one line otherwise)."""
    if str(name_or_path) not in WEIGHTS and not Path(name_or_path).is_file():
        raise InputError(f"{name_or_path}: no such lip model file (the shipped ones: {', '.join(WEIGHTS)})")


def describe_weights(name_or_path: str | Path) -> str:
    """What a lip model's weights are, in a few words (a record's stand-in line)."""
    if str(name_or_path) == DEFAULT:
        return "pretrained on generated voices, adapted on real speakers' lip tracks"
    if str(name_or_path) in WEIGHTS:
        return WEIGHTS[str(name_or_path)][0]
    held = held_out(name_or_path)
    return (f"weights {Path(name_or_path).name}, sha256 {weights_sha256(name_or_path)[:12]}..."
            + (f", adapted with {', '.join(held)} held out" if held else ""))


def held_out(name_or_path: str | Path) -> list[str]:
    """The clips a lip model's weights file was adapted without, by its ``<file>.json`` ([] where it names none)."""
    entry = _provenance(name_or_path)
    return [str(c) for c in (entry or {}).get("held_out", [])]


def adapted_on(name_or_path: str | Path) -> list[dict] | None:
    """The real recordings a lip model was adapted on (``clip``, ``sha256`` of the video file, ``frames``), from
    :data:`PROVENANCE` beside the shipped files or ``<file>.json`` beside another; None where nothing says."""
    clips = (_provenance(name_or_path) or {}).get("adapted_on")
    return None if clips is None else [dict(c) for c in clips]


def _provenance(name_or_path: str | Path) -> dict | None:
    """A lip model's provenance entry: its key in :data:`PROVENANCE` for a shipped name, else ``<file>.json``; None
    where there is none."""
    import json

    name = str(name_or_path)
    f = FOLDER / PROVENANCE if name in WEIGHTS else Path(name + ".json")
    if not f.is_file():
        return None
    try:
        doc = json.loads(f.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{f}: not a lip model provenance file ({exc})") from None
    return doc.get(name, {}) if name in WEIGHTS else doc


def write_provenance(path: str | Path, clips: Sequence[dict], held_out: Sequence[str] = ()) -> None:
    """``<path>.json``: the recordings a weights file at ``path`` was adapted on and the clips held out of it."""
    _write_json(Path(str(path) + ".json"), {"adapted_on": [dict(c) for c in clips], "held_out": list(held_out)})


def write_shipped_provenance(folder: str | Path, clips: Sequence[dict]) -> None:
    """:data:`PROVENANCE` in ``folder`` for the shipped pair: ``lips_generated.pt`` adapted on nothing real,
    ``lips_generic.pt`` on ``clips``."""
    _write_json(Path(folder) / PROVENANCE, {"lips_generated.pt": {"adapted_on": []},
                                            "lips_generic.pt": {"adapted_on": [dict(c) for c in clips]}})


def _write_json(path: Path, doc: dict) -> None:
    import json

    from lmgs.fileio import atomic_write

    atomic_write(path, (json.dumps(doc, indent=1, sort_keys=True) + "\n").encode())
