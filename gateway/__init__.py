"""Polling gateway for RS485 water-quality sensors: Modbus RTU in, MQTT and Prometheus out."""

__version__ = "0.1.0"
