"""A reload, recorded: the config file's hash, what changed, or why it was refused.

A reload changes what the gateway writes into sensors (feeds, flash allow-lists, the
pinned serial numbers), so an auditor asks when the config changed and to what: the
SHA-256 of the file as read lets a copy of the file be matched with the record.
"""

from __future__ import annotations

import hashlib
import logging
from typing import TYPE_CHECKING

from gateway.errors import RecordError
from gateway.records.actor import Actor, Via
from gateway.records.model import Entry, Kind, Result

if TYPE_CHECKING:
    from collections.abc import Sequence
    from pathlib import Path

    from gateway.records.store import RecordStore

_LOGGER = logging.getLogger(__name__)

RELOAD_ACTOR = Actor(
    user="gateway",
    via=Via.GATEWAY,
    detail="reload (SIGHUP: systemctl reload or gateway reload)",
)


def file_sha256(path: Path) -> str | None:
    """The SHA-256 of a file's bytes, ``None`` if it cannot be read."""
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def record_reload(
    store: RecordStore,
    path: Path,
    *,
    summary: str = "",
    problems: Sequence[str] = (),
    applied: str = "",
) -> None:
    """One record of a reload: applied (with what changed) or refused (with its problems)."""
    if problems and not applied:
        result, note = Result.FAILED, "refused; the running config stays"
    elif problems:
        result, note = Result.FAILED, f"applied {applied}"
    else:
        result, note = Result.DONE, summary
    try:
        store.append(
            Entry(
                kind=Kind.RELOAD,
                actor=RELOAD_ACTOR,
                action="reload the config",
                result=result,
                note=note,
                data={
                    "file": str(path),
                    "sha256": file_sha256(path),
                    "changes": summary or None,
                    "problems": list(problems),
                },
            )
        )
    except RecordError as exc:
        _LOGGER.warning("the reload was not recorded: %s", exc)
