"""The store-and-forward queue: order, bound, retained superseding, persistence."""

from __future__ import annotations

from typing import TYPE_CHECKING

import pytest

from gateway.errors import PublishError
from gateway.publish.message import Message
from gateway.publish.store import MessageStore

if TYPE_CHECKING:
    from pathlib import Path


def msg(topic: str, payload: str, *, retain: bool = False) -> Message:
    return Message.text(topic, payload, retain=retain)


def test_messages_come_out_in_order_and_survive_a_restart(tmp_path: Path) -> None:
    store = MessageStore(tmp_path / "q.sqlite", max_messages=100)
    store.append([msg("a/state", str(n)) for n in range(10)])
    assert len(store) == 10
    first = store.peek(3)
    store.remove([i for i, _ in first])
    store.close()
    reopened = MessageStore(tmp_path / "q.sqlite", max_messages=100)
    assert len(reopened) == 7
    assert [m.payload for _, m in reopened.peek(100)] == [str(n).encode() for n in range(3, 10)]


def test_the_bound_drops_the_oldest_non_retained_and_counts_them(tmp_path: Path) -> None:
    store = MessageStore(tmp_path / "q.sqlite", max_messages=5)
    store.append([msg("gw/status", "online", retain=True)])
    dropped = store.append([msg("gw/d/state", str(n)) for n in range(8)])
    assert dropped == 4
    assert store.dropped == 4
    assert len(store) == 5
    payloads = [m.payload.decode() for _, m in store.peek(10)]
    assert payloads == ["online", "4", "5", "6", "7"]


def test_a_retained_message_supersedes_the_older_one_on_its_topic(tmp_path: Path) -> None:
    store = MessageStore(tmp_path / "q.sqlite", max_messages=100)
    store.append([msg("gw/d/temperature", "20.1", retain=True), msg("gw/d/state", "1")])
    store.append([msg("gw/d/temperature", "20.2", retain=True), msg("gw/d/state", "2")])
    contents = [(m.topic, m.payload.decode()) for _, m in store.peek(10)]
    assert contents == [("gw/d/state", "1"), ("gw/d/temperature", "20.2"), ("gw/d/state", "2")]
    assert len(store) == 3


def test_removing_an_id_that_was_superseded_keeps_the_count(tmp_path: Path) -> None:
    store = MessageStore(tmp_path / "q.sqlite", max_messages=100)
    store.append([msg("gw/d/temperature", "20.1", retain=True)])
    in_flight = store.peek(1)
    store.append([msg("gw/d/temperature", "20.2", retain=True)])
    store.remove([i for i, _ in in_flight])
    assert len(store) == 1
    assert store.peek(1)[0][1].payload == b"20.2"


def test_an_unwritable_state_directory_is_a_clear_error(tmp_path: Path) -> None:
    blocked = tmp_path / "blocked"
    blocked.write_text("not a directory", encoding="utf-8")
    with pytest.raises(PublishError, match="cannot be written"):
        MessageStore(blocked / "q.sqlite", max_messages=100)
