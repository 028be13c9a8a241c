"""MQTT: the contract's topics, publish modes, and store-and-forward across broker outages.

Topics under ``{base}``: ``{base}/{device}/{point}`` plain value (retained),
``{base}/{device}/state`` one JSON document per poll cycle, ``{base}/{device}/status/{flag}``
``true``/``false`` per named status or error bit (retained), ``{base}/{device}/availability``
``online``/``offline`` (retained) and ``{base}/status`` for the gateway itself (the last will).

The pieces: what is sent where (value topics, status bits, state documents, availability,
retained clears, discovery) in :mod:`~gateway.publish.mqtt.topics`, built without I/O; the
messages on their way (the live queue, the disk backlog, the in-flight window) in
:mod:`~gateway.publish.mqtt.outbox`; the session with the broker (reconnects, subscriptions,
``online``/``offline``, commands coming in for each :class:`Listener`) in
:mod:`~gateway.publish.mqtt.connection`; Home Assistant's restart answered with the discovery
again, after a random wait, in :mod:`~gateway.publish.mqtt.reannounce`; and :class:`MqttSink`,
the sink that joins them, in :mod:`~gateway.publish.mqtt.sink`.
"""

from gateway.publish.mqtt.connection import Listener
from gateway.publish.mqtt.sink import MqttSink

__all__ = ["Listener", "MqttSink"]
