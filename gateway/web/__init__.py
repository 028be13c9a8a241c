"""The page in the browser, served by the gateway itself.

Live values, sensor care, a device's register map, bus health, guided calibration and a
scan of an idle line.

The pieces: who may do what in :mod:`~gateway.web.auth`, what the page shows in
:mod:`~gateway.web.live` (sensor care's view in :mod:`~gateway.web.care`), the
calibrations in :mod:`~gateway.web.calibration`, the scan of a line in
:mod:`~gateway.web.scan`, and the HTTP server with its routes in
:mod:`~gateway.web.site`; the page itself is ``static/`` (hand-written HTML, CSS and
JavaScript, no build step). Import from here.
"""

from gateway.web.auth import Sessions
from gateway.web.scan import LineScans
from gateway.web.site import WebServer

__all__ = ["LineScans", "Sessions", "WebServer"]
