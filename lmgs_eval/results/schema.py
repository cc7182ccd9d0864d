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

__all__ = ["FAMILIES", "PROTOCOLS", "READ_VERSIONS", "SCHEMA_VERSION", "validate"]


def validate(record: Any) -> list[str]:
    """Check a record against its types (:class:`~lmgs_eval.results.types.Record`) and a few cross-field rules.

    Args:
        record: a decoded JSON object.

    Returns:
        Problems, one line each naming the field (``record.metrics.psnr.value: ...``);
        empty when the record is valid.
    """
    out: list[str] = []
    decode(Record, record, "record", out)
    if out or not isinstance(record, dict):
        return out
    if record["schema_version"] not in READ_VERSIONS:
        return [f"record.schema_version: {record['schema_version']!r} is not one of {', '.join(READ_VERSIONS)}"]
    for key, m in record["metrics"].items():
        if m["n_effective"] > m["n_original"]:
            out.append(f"record.metrics.{key}: n_effective {m['n_effective']} > n_original {m['n_original']}")
    status = record.get("status") or {}
    if status.get("state") == "failed" and not status.get("reason"):
        out.append("record.status.reason: a failed run must say why")
    return out
