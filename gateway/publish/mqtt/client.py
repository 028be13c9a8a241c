"""aiomqtt's client, mended where a connection attempt fails or is cancelled.

aiomqtt 2.5.1 leaves the socket of a failed attempt open and watched by the event loop,
and when the attempt was cancelled (a stop or a reload while connecting; a broker that took
longer than the connect timeout to answer, in one ordering of the loop's callbacks), the
socket's next read raised ``CancelledError`` out of its disconnect callback: the log showed
asyncio's "Exception in callback" with a traceback. It was seen with a clustered broker
(NATS) that answered CONNECT slowly while it elected a leader. Left open, the attempt's
socket could also complete a session on that server later, under the gateway's client id,
beside the one it made on the next server.

Both are mended here, at the one place where the gateway makes a client, so that the
reconnect loops above it see only :class:`aiomqtt.MqttError` and a closed socket.
"""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING, Any, Self

import aiomqtt

if TYPE_CHECKING:
    import paho.mqtt.client as mqtt
    from paho.mqtt.properties import Properties
    from paho.mqtt.reasoncodes import ReasonCode


class BrokerClient(aiomqtt.Client):
    """An :class:`aiomqtt.Client` whose failed or cancelled connection attempt is closed."""

    async def __aenter__(self) -> Self:
        """Connect; on any failure, close the attempt's socket before raising."""
        try:
            return await super().__aenter__()
        except BaseException:
            self._close_attempt()
            raise

    def _close_attempt(self) -> None:
        # paho's own close: it also unregisters the socket from the loop (aiomqtt's
        # socket-close callback) and stops aiomqtt's housekeeping task.
        # A client is not entered again after a failed attempt: the gateway makes a new one.
        with contextlib.suppress(OSError):
            self._client._sock_close()  # noqa: SLF001 - paho has no public close without a DISCONNECT

    def _on_disconnect(
        self,
        client: mqtt.Client,
        userdata: Any,  # noqa: ANN401 - paho's user data, as aiomqtt types it
        flags: mqtt.DisconnectFlags,
        reason_code: ReasonCode,
        properties: Properties | None = None,
    ) -> None:
        # aiomqtt asks a cancelled attempt's future for its exception, which raises.
        if self._connected.cancelled():
            return
        super()._on_disconnect(client, userdata, flags, reason_code, properties)


__all__ = ["BrokerClient"]
