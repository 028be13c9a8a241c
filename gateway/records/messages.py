"""The records on MQTT: each one for a plant historian, and the chain's head, retained.

``{base}/records``: every record as it is appended, non-retained at QoS 1 (a historian
subscribed keeps its own copy; the gateway's MQTT queue holds them through an outage).
A write is two records, the write before it is sent and its outcome after, linked by the
outcome's ``completes``. ``{base}/records/head``: the newest record's number and hash,
retained: a copy kept anywhere else proves later that nothing before it was rewritten
(``gateway records verify --head SEQ:HASH``).
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Final

from gateway.publish.message import Message

if TYPE_CHECKING:
    from gateway.records.chain import Head
    from gateway.records.model import Record

RECORDS_TOPIC: Final = "records"
HEAD_TOPIC: Final = "records/head"


def record_message(base_topic: str, record: Record) -> Message:
    """One record as its non-retained QoS 1 message: its content, number and hash."""
    payload = {**record.body, "hash": record.hash}
    return Message(
        topic=f"{base_topic}/{RECORDS_TOPIC}",
        payload=json.dumps(payload, ensure_ascii=False, separators=(",", ":")).encode(),
        qos=1,
        retain=False,
    )


def head_message(base_topic: str, head: Head, *, time: str = "") -> Message:
    """The chain's head as its retained message."""
    payload = {"seq": head.seq, "hash": head.hash, "time": time or None}
    return Message(
        topic=f"{base_topic}/{HEAD_TOPIC}",
        payload=json.dumps(payload, separators=(",", ":")).encode(),
        qos=1,
        retain=True,
    )
