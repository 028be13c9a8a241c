"""The shared bus: other masters reach the sensors through the gateway (Modbus TCP server)."""

from gateway.control.shared_bus.policy import units
from gateway.control.shared_bus.server import SharedBusServer

__all__ = ["SharedBusServer", "units"]
