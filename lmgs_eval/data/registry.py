"""Finding subjects by name or path, and building bundled subjects on first use.

Lookup order for ``--subject X``:

1. ``X`` is an existing folder: read it (``--subject path/to/folder``).
2. ``X`` names a bundled subject (``astronaut``, ``hopper``, or a sized variant such as
   ``astronaut-64px-2s``): built under the data root on first use, then read.
3. ``X`` is a folder under the data root (``obama``, ``may``, ``lieu`` or any other).
4. Otherwise: a one-line error that says where it looked and what is known.
"""

from __future__ import annotations

import fcntl
import json
import sys
from pathlib import Path

from lmgs_eval.data import bundled
from lmgs_eval.data.bundled_spec import BUNDLED, BundledSpec
from lmgs_eval.data.layout import read_subject
from lmgs_eval.data.subject import Subject
from lmgs_eval.errors import UserError
from lmgs_eval.paths import atomic_dir, data_root

# The paper's subjects: recognised by name, never shipped.
PAPER_SUBJECTS = {
    "obama": "AD-NeRF's Obama video (450x450)",
    "may": "GeneFace's May video (512x512)",
    "lieu": "GeneFace's Lieu video (512x512)",
}


def _generator_version() -> str:
    return bundled.GENERATOR_VERSION


def ensure_bundled(spec: BundledSpec, root: Path | None = None, *, force: bool = False, progress: bool = True) -> Path:
    """Build a bundled subject if it is missing or was made by another generator version.

    The build runs in a temporary folder renamed at the end, under a lock file, so an
    interrupted build leaves nothing half-written and two processes never build twice.
    """
    if spec.size < 32 or spec.size > 2048:
        raise UserError(f"--size {spec.size}: must be between 32 and 2048 pixels")
    if not (1.0 <= spec.seconds <= 600.0):
        raise UserError(f"--seconds {spec.seconds:g}: must be between 1 and 600")
    root = data_root(root)
    root.mkdir(parents=True, exist_ok=True)
    final = root / spec.folder
    with open(root / f".{spec.folder}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        meta = final / "meta.json"
        if final.is_dir() and meta.exists() and not force:
            try:
                version = json.loads(meta.read_text()).get("generator_version")
            except json.JSONDecodeError:
                version = None
            if version == bundled.GENERATOR_VERSION and bundled.speech_is_shipped(final):
                return final
            if version == bundled.GENERATOR_VERSION:
                print(f"{final}: its piper speech is not the shipped samples (built on this CPU before they were "
                      f"shipped), rebuilding", file=sys.stderr)
            else:
                print(f"{final}: built by generator {version}, rebuilding with {bundled.GENERATOR_VERSION}", file=sys.stderr)
        with atomic_dir(final) as tmp:
            bundled.build(spec.name, tmp, size=spec.size, seconds=spec.seconds, seed=spec.seed, progress=progress)
    return final


def resolve_subject_dir(subject: str, root: str | Path | None = None, *, build: bool = True, progress: bool = True) -> Path:
    """The folder of ``subject`` (a path, a bundled name, or a folder under the data root)."""
    p = Path(subject).expanduser()
    if p.is_dir():
        return p
    droot = data_root(root)
    spec = BundledSpec.parse(subject)
    if spec is not None:
        if build:
            return ensure_bundled(spec, droot, progress=progress)
        return droot / spec.folder
    cand = droot / subject
    if cand.is_dir():
        return cand
    if subject.lower() in PAPER_SUBJECTS:
        raise UserError(
            f"subject '{subject}' not found at {cand}: process {PAPER_SUBJECTS[subject.lower()]} with ER-NeRF's "
            f"data_utils/process.py and put the folder there (or pass --subject PATH / --data-root DIR / set LMGS_DATA)"
        )
    if "/" in subject or subject.startswith("."):
        raise UserError(f"{p}: subject folder not found")
    known = ", ".join(list(BUNDLED) + sorted(d.name for d in _found_dirs(droot)))
    raise UserError(f"unknown subject '{subject}' (looked in {droot}); known: {known}")


def find_subject(subject: str, root: str | Path | None = None, *, progress: bool = True) -> Subject:
    """Read a subject by name or path, building a bundled one on first use."""
    folder = resolve_subject_dir(subject, root, progress=progress)
    return read_subject(folder, name=folder.name)


def _found_dirs(root: Path) -> list[Path]:
    if not root.is_dir():
        return []
    return [d for d in sorted(root.iterdir()) if d.is_dir() and not d.name.startswith(".") and (d / "transforms_train.json").exists()]


def list_subjects(root: str | Path | None = None) -> list[dict]:
    """Every bundled subject (built or not) and every subject folder found under the data root."""
    droot = data_root(root)
    rows: list[dict] = []
    seen: set[str] = set()
    for d in _found_dirs(droot):
        seen.add(d.name)
        try:
            s = read_subject(d, check_images=False, derive=False)
            row = {**s.describe(), "built": True, "status": "ok"}
        except UserError as exc:
            row = {"name": d.name, "path": str(d), "built": True, "status": f"error: {exc}"}
        rows.append(row)
    for name in BUNDLED:
        if name not in seen:
            rows.append({"name": name, "path": str(droot / name), "built": False, "bundled": True,
                         "status": f"not built (lmgs-eval prepare --subject {name})"})
    for name, what in PAPER_SUBJECTS.items():
        if name not in seen:
            rows.append({"name": name, "path": str(droot / name), "built": False, "bundled": False,
                         "status": f"not found: process {what} with ER-NeRF's data_utils/process.py"})
    return rows
