"""The running gateway: what a config builds, run under one supervisor, reloaded in place.

- :mod:`gateway.app.build`: the parts one config builds (workers, write paths, sinks, ...);
- :mod:`gateway.app.running`: :class:`~gateway.app.running.RunningGateway`, those parts
  started, supervised and changed by a reload, and :func:`run`;
- :mod:`gateway.app.reload`: how a reload is asked for (SIGHUP, ``gateway reload``) and
  told (its status for ``/healthz``, the metrics and the command);
- :mod:`gateway.app.logs`: the log's format.
"""

from gateway.app.build import build_workers, build_writers, device_target, state_directory
from gateway.app.logs import configure_logging
from gateway.app.running import run

__all__ = [
    "build_workers",
    "build_writers",
    "configure_logging",
    "device_target",
    "run",
    "state_directory",
]
