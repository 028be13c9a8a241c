"""A sensor simulator: every family's behaviour on a strict, refereed Modbus RTU line."""

from gateway.simulator.bus import FaultPlan, Reply, SimulatedBus, Violation
from gateway.simulator.config import (
    DeviceSettings,
    SimulationSettings,
    build_bus,
    load_settings,
    parse_device_option,
    parse_settings,
)
from gateway.simulator.device import SimulatedDevice, SlaveExceptionError
from gateway.simulator.transport import SimulatorError, SimulatorServer

__all__ = [
    "DeviceSettings",
    "FaultPlan",
    "Reply",
    "SimulatedBus",
    "SimulatedDevice",
    "SimulationSettings",
    "SimulatorError",
    "SimulatorServer",
    "SlaveExceptionError",
    "Violation",
    "build_bus",
    "load_settings",
    "parse_device_option",
    "parse_settings",
]
