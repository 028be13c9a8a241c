"""The gateway's exception tree: one root, context carried as attributes.

::

    GatewayError
    ├── ConfigError                 a config file or setting is wrong (key path, line)
    ├── ProfileError                a profile data file is wrong (file, point, problem)
    ├── CodecError
    │   ├── DecodeError             registers that cannot be a value of the point's type
    │   └── EncodeError             a value that cannot be written to the point
    ├── FrameError                  bytes on the wire that are not the expected answer
    │   ├── CrcError                checksum mismatch
    │   ├── UnexpectedDeviceError   an answer from another device address
    │   ├── MalformedFrameError     wrong function code, byte count or length
    │   └── EchoMismatchError       the adapter's echo of a request differs from what was sent
    ├── DeviceExceptionError        the device answered with a Modbus exception code
    ├── BusError                    the line itself
    │   ├── BusTimeoutError         no (complete) answer in time
    │   │   ├── LineNoiseError      the line never fell silent: the request was not sent
    │   │   └── ConverterError      a Modbus TCP converter answered for the device
    │   │       ├── ConverterPathError      0A: it has no path to the line
    │   │       └── ConverterNoAnswerError  0B: the device did not answer it
    │   ├── BusClosedError          the port is closed or went away
    │   │   └── PortUnavailableError    the port cannot be opened: ``.reason`` says why
    │   └── BusBusyError            no bus time for another master's request now
    ├── PublishError                a sink could not deliver
    ├── CommandRejectedError        a write command failed validation; nothing was sent
    ├── RecordError                 the record store cannot be written or read
    ├── CalibrationInterruptedError a calibration stopped part-way (what was written)
    └── OperationTimeoutError       an operation's device did not get there in time

Foreign exceptions (pymodbus, pyserial, yaml) are translated into these at exactly
one boundary each, with ``raise ... from exc``.
"""

from __future__ import annotations


class GatewayError(Exception):
    """Root of every error the gateway raises on purpose."""


class ConfigError(GatewayError):
    """A configuration problem, located by key path and, where known, file line."""

    def __init__(self, message: str, *, key: str = "", line: int | None = None) -> None:
        """Keep the key path and line so callers can point at the offending spot."""
        self.key = key
        self.line = line
        where = key + (f" (line {line})" if line is not None else "")
        super().__init__(f"{where}: {message}" if where else message)


class ProfileError(GatewayError):
    """A profile data file that does not describe a consistent register map."""

    def __init__(self, message: str, *, source: str, point: str = "") -> None:
        """Name the file and point so a profile author can find the problem at once."""
        self.source = source
        self.point = point
        where = f"{source}: point {point!r}" if point else source
        super().__init__(f"{where}: {message}")


class CodecError(GatewayError):
    """Registers and values that do not fit a point's data type."""


class DecodeError(CodecError):
    """The registers read cannot be a value of the point's type."""


class EncodeError(CodecError):
    """The value cannot be written to the point: wrong type, out of range, too long."""


class FrameError(GatewayError):
    """Bytes on the wire that are not the answer to the request in flight."""


class CrcError(FrameError):
    """The frame's CRC does not match its content."""


class UnexpectedDeviceError(FrameError):
    """A well-formed frame from a device address other than the one asked."""

    def __init__(self, message: str, *, expected: int, received: int) -> None:
        """Keep both addresses for counting and logs."""
        self.expected = expected
        self.received = received
        super().__init__(message)


class MalformedFrameError(FrameError):
    """Wrong function code, byte count or length for the request in flight."""


class EchoMismatchError(FrameError):
    """The bytes read back after sending were not the request (``echo: on``).

    Another master or a collision changed them on the line, or the adapter does not echo.
    """


class DeviceExceptionError(GatewayError):
    """The device answered with a Modbus exception response."""

    def __init__(self, *, device: int, function: int, code: int, meaning: str) -> None:
        """Keep the exception code and the family's meaning of it."""
        self.device = device
        self.function = function
        self.code = code
        self.meaning = meaning
        super().__init__(
            f"device {device} answered function {function:#04x} with exception "
            f"{code:02d} ({meaning})"
        )


class BusError(GatewayError):
    """A problem with the line itself rather than one device's answer."""


class BusTimeoutError(BusError):
    """No complete answer arrived within the response timeout."""


class LineNoiseError(BusTimeoutError):
    """The line never fell silent for the inter-frame gap: the request was not sent.

    A timeout as far as the device is concerned (no answer could come), and an error kind
    of its own on the line: termination, biasing, earthing or another master.
    """


class ConverterError(BusTimeoutError):
    """A serial device server in Modbus TCP mode answered for the device: it could not.

    The converter's exceptions 0A and 0B say nothing of the device's registers, only that
    no answer came from it on the serial side: a failure like a timeout (counted towards
    offline, retried, the late-answer window kept), never a device exception that would
    split a read. ``code`` is the exception code, ``kind`` its name in the error counts.
    """

    kind = "converter"

    def __init__(self, message: str, *, device: int, code: int) -> None:
        """Keep the device address and the converter's exception code."""
        self.device = device
        self.code = code
        super().__init__(message)


class ConverterPathError(ConverterError):
    """Exception 0A, gateway path unavailable: the converter has no way to the line."""

    kind = "gateway_path_unavailable"


class ConverterNoAnswerError(ConverterError):
    """Exception 0B, gateway target device failed to respond (within the converter's timeout)."""

    kind = "gateway_target_failed"


class BusClosedError(BusError):
    """The port is closed locally or went away (adapter unplugged)."""


class PortUnavailableError(BusClosedError):
    """The port cannot be opened, for a reason the user can act on.

    ``reason`` is one of ``missing``, ``permission_denied``, ``in_use``, ``no_rs485_mode``
    or ``driver_error`` (:class:`gateway.line.transports.port_diagnosis.PortReason`):
    callers (the bus worker, ``/healthz``, the command line) branch on it, never on the
    message's text.
    """

    def __init__(self, message: str, *, port: str, reason: str, holder: int | None = None) -> None:
        """Keep the port, why it is not open and, if in use, the process that holds it."""
        self.port = port
        self.reason = reason
        self.holder = holder
        super().__init__(message)


class BusBusyError(BusError):
    """Another master's request found no bus time: its share is spent or its queue full."""


class PublishError(GatewayError):
    """A sink could not deliver a sample."""


class CommandRejectedError(GatewayError):
    """A write command failed validation; nothing reached the bus."""

    def __init__(self, reason: str, *, point: str = "") -> None:
        """Keep the reason for the result topic."""
        self.reason = reason
        self.point = point
        super().__init__(f"{point}: {reason}" if point else reason)


class RecordError(GatewayError):
    """The record store cannot be written (so the act it would record is not done) or read."""


class CalibrationInterruptedError(GatewayError):
    """A calibration stopped part-way through its writes; ``written`` lists what went out.

    A separate kind from :class:`CommandRejectedError`, which promises that nothing was
    sent: here the device may hold part of a calibration, and the message says what to do.
    """

    def __init__(self, message: str, *, written: tuple[str, ...], failed: str) -> None:
        """Keep the points written before the failure and the point that failed."""
        self.written = written
        self.failed = failed
        super().__init__(message)


class OperationTimeoutError(GatewayError):
    """An operation's device did not reach the awaited state in time (the write was sent)."""
