"""Which records this code reads and writes, and the check every record passes on write and on read.

The record's fields are the typed dataclasses of :mod:`lmgs_eval.results.types`; this module
adds the schema versions and the rules that tie fields together.
"""

from __future__ import annotations

from typing import Any

from lmgs_eval.results.types import FAMILIES, PROTOCOLS, Record, decode

SCHEMA_VERSION = "2"
"""Written by this code. Version 2 added ``method.components`` and ``run`` (structured facts that
version 1 kept in prose notes or left to be read out of a method's config)."""
READ_VERSIONS = ("1", SCHEMA_VERSION)
"""Read by this code; older records are migrated on read (:mod:`lmgs_eval.results.migrate`)."""

__all__ = ["FAMILIES", "PROTOCOLS", "READ_VERSIONS", "SCHEMA_VERSION", "check", "validate"]


def check(record: Any) -> tuple[Record | None, list[str]]:
    """A decoded JSON object as a typed :class:`~lmgs_eval.results.types.Record`, checked against its types
    and a few cross-field rules (a typed record is checked in its JSON form).

    Returns:
        The typed record (None when it does not fit) and the problems, one line each naming the
        field (``record.metrics.psnr.value: ...``); no problems when the record is valid.
    """
    out: list[str] = []
    rec = decode(Record, record.to_dict() if isinstance(record, Record) else record, "record", out)
    if out or rec is None:
        return None, out
    if rec.schema_version not in READ_VERSIONS:
        return None, [f"record.schema_version: {rec.schema_version!r} is not one of {', '.join(READ_VERSIONS)}"]
    for key, m in rec.metrics.items():
        if m.n_effective > m.n_original:
            out.append(f"record.metrics.{key}: n_effective {m.n_effective} > n_original {m.n_original}")
    if rec.failed and not rec.status.reason:
        out.append("record.status.reason: a failed run must say why")
    return (None if out else rec), out


def validate(record: Any) -> list[str]:
    """The problems :func:`check` finds in a decoded JSON object (empty when the record is valid)."""
    return check(record)[1]
