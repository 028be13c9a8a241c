"""Sparkplug B: the gateway as an edge node for SCADA and MES plant systems.

Topics ``spBv1.0/{group}/{NBIRTH|NDATA|NDEATH|NCMD|DBIRTH|DDATA|DDEATH|DCMD}/{edge}[/{device}]``
and the primary host's ``spBv1.0/STATE/{host}``; payloads per Eclipse Tahu's
``sparkplug_b.proto`` (Sparkplug 3.0.0), vendored here with its generated code.

The pieces: the schema's messages built and read (:mod:`~gateway.publish.sparkplug.payloads`);
the topics (:mod:`~gateway.publish.sparkplug.topics`); the metrics, their aliases, types and
deadbands (:mod:`~gateway.publish.sparkplug.catalogue`); births, report-by-exception data and
deaths (:mod:`~gateway.publish.sparkplug.reports`); the session with its will, ``bdSeq``,
``seq``, primary host and store and forward (:mod:`~gateway.publish.sparkplug.session`); and
:class:`SparkplugSink`, which joins them (:mod:`~gateway.publish.sparkplug.sink`). Commands
that write (DCMD) are the control floor's: ``gateway.control.sparkplug_commands``.
"""

from gateway.publish.sparkplug.sink import SparkplugSink

__all__ = ["SparkplugSink"]
