"""The records: every change to a sensor and every grab-sample check, as an auditor accepts them.

Who did it and why (:mod:`~gateway.records.actor`), what a record says
(:mod:`~gateway.records.model`), the hash chain and its check
(:mod:`~gateway.records.chain`), the append-only store in the state directory
(:mod:`~gateway.records.store`), compensation feeds counted per day
(:mod:`~gateway.records.feeds`). Import from here.
"""

from gateway.records.actor import Actor, Via, acting, current
from gateway.records.chain import Head, Verdict
from gateway.records.feeds import FeedCounts
from gateway.records.model import DeviceRef, Entry, Kind, PointChange, Record, Result
from gateway.records.store import Query, RecordStore, records_path

__all__ = [
    "Actor",
    "DeviceRef",
    "Entry",
    "FeedCounts",
    "Head",
    "Kind",
    "PointChange",
    "Query",
    "Record",
    "RecordStore",
    "Result",
    "Verdict",
    "Via",
    "acting",
    "current",
    "records_path",
]
