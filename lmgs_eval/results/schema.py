"""Which records this code reads and writes, and the check every record passes on read.

The record's fields are the typed dataclasses of :mod:`lmgs_eval.results.types`, each checking
itself when it is made (its types, its constraints, the rules that tie its fields together);
this module names the schema versions and checks a record's JSON form by making it.
"""

from __future__ import annotations

from typing import Any

from lmgs_eval.results.types import FAMILIES, PROTOCOLS, READ_VERSIONS, SCHEMA_VERSION, Record, decode_record

__all__ = ["FAMILIES", "PROTOCOLS", "READ_VERSIONS", "SCHEMA_VERSION", "check", "validate"]


def check(record: Any) -> tuple[Record | None, list[str]]:
    """A decoded JSON object as a typed :class:`~lmgs_eval.results.types.Record`, made (so checked) from it.

    Returns:
        The typed record (None when it does not fit) and the problems, one line each naming the
        field (``record.metrics.psnr.value: ...``); no problems when the record is valid. A typed
        record was checked when it was made: it is handed back as it is.
    """
    if isinstance(record, Record):
        return record, []
    return decode_record(record)


def validate(record: Any) -> list[str]:
    """The problems :func:`check` finds in a decoded JSON object (empty when the record is valid)."""
    return check(record)[1]
