"""The line's transports: RTU on a serial port or through a converter, Modbus TCP; their ports."""
