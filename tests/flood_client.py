"""Another master that pipelines Modbus TCP requests as fast as TCP takes them, in a process of its own.

Run by the shared-bus load tests as ``python -m tests.flood_client``: a flood sent from the
tests' own event loop would compete with the gateway for that loop and the GIL, and so
measure the test rather than the gateway. One thread writes the same request over and
over (transaction ids counting up), another reads and tallies the answers; after
``--seconds`` it prints one JSON line and aborts the connection, whatever is still queued.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import select
import socket
import struct
import sys
import threading
import time
from collections import Counter

BATCH = 64  # requests per sendall


def _reader(sock: socket.socket, tally: Counter[str], stop: threading.Event) -> None:
    buffer = b""
    while not stop.is_set():
        if not select.select([sock], [], [], 0.1)[0]:
            continue
        try:
            chunk = sock.recv(65536)
        except OSError:
            return
        if not chunk:
            tally["eof"] += 1
            return
        buffer += chunk
        while len(buffer) >= 6:  # the MBAP header up to its length
            length = int.from_bytes(buffer[4:6], "big")
            if len(buffer) < 6 + length:
                break
            pdu, buffer = buffer[7 : 6 + length], buffer[6 + length :]
            tally[pdu[:2].hex() if pdu[0] & 0x80 else f"{pdu[0]:02x}"] += 1


def _writer(sock: socket.socket, unit: int, pdu: bytes, sent: list[int]) -> None:
    while True:
        batch = b"".join(
            struct.pack(">HHHB", (sent[0] + n) & 0xFFFF, 0, len(pdu) + 1, unit) + pdu
            for n in range(BATCH)
        )
        try:
            sock.sendall(batch)  # blocks while the gateway reads no more: backpressure
        except OSError:
            return
        sent[0] += BATCH


def flood(port: int, unit: int, pdu: bytes, seconds: float) -> dict[str, object]:
    """Pipeline ``pdu`` to ``unit`` for ``seconds``: the requests sent and answers by kind.

    Blocking sockets in threads of their own (also what ``bench/shared_bus.py`` runs), so
    the flood never waits on an event loop.
    """
    sock = socket.create_connection(("127.0.0.1", port))
    tally: Counter[str] = Counter()
    sent = [0]
    stop = threading.Event()
    reader = threading.Thread(target=_reader, args=(sock, tally, stop), daemon=True)
    writer = threading.Thread(target=_writer, args=(sock, unit, pdu, sent), daemon=True)
    reader.start()
    writer.start()
    print("connected", flush=True)  # noqa: T201 - the test waits for this line
    time.sleep(seconds)
    stop.set()
    reader.join(timeout=1.0)
    # A writer blocked by the gateway's backpressure wakes on the shutdown; the abort
    # (RST) drops whatever is still queued.
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)
    writer.join(timeout=1.0)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()
    return {"sent": sent[0], "answers": dict(tally)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--unit", type=int, required=True)
    parser.add_argument("--pdu", default="0300000002")
    parser.add_argument("--seconds", type=float, default=3.0)
    args = parser.parse_args()
    result = flood(args.port, args.unit, bytes.fromhex(args.pdu), args.seconds)
    json.dump(result, sys.stdout)
    print(flush=True)  # noqa: T201


if __name__ == "__main__":
    main()
