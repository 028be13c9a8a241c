"""The wire: line timing, Modbus RTU frames and the codec of register values (pure)."""
