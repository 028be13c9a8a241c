"""The shared bus: other masters reach the sensors through the gateway (Modbus TCP server)."""

from gateway.control.shared_bus.listener import SharedBusServer
from gateway.control.shared_bus.policy import units

__all__ = ["SharedBusServer", "units"]
