"""One device from the command line: the options that name it and the link that reaches it.

The commands that act on one sensor (``write``, ``calibrate``, the operations) take the
same options: either ``--config FILE --device NAME`` (the line, address, profile, timing
overrides, flash allow-list and ledger of a configured device), or the line and device
spelt out (``--port``, ``--address``, ``--profile`` and the line format). The command
line opens the port itself: stop a gateway that polls the same port first, or send the
command over MQTT instead.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, TypeVar, get_type_hints

import typer
from rich.console import Console
from rich.markup import escape

from gateway.app import device_target, state_directory
from gateway.config import DEFAULT_FLASH_WRITE_BUDGET, FlashPolicy, load_config
from gateway.config.echo import EchoMode
from gateway.control.flash import LEDGER_FILE, FlashLedger
from gateway.control.link import DeviceLink, open_link
from gateway.control.ports import port_options
from gateway.errors import ConfigError, GatewayError
from gateway.line.engine.devices import DeviceTarget
from gateway.line.transports.port_access import PortOptions
from gateway.profiles import get_profile
from gateway.records import RecordStore, records_path
from gateway.shared.host_clock import HostClock
from gateway.wire import codec
from gateway.wire.timing import LineFormat

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable

    from gateway.config.network import TcpSettings

_R = TypeVar("_R")


out = Console(highlight=False, soft_wrap=True)
err = Console(stderr=True, highlight=False)


def fail(exc: GatewayError, *, code: int = 2) -> typer.Exit:
    """Print an error as the command line does everywhere; raise what it returns.

    Exit code 2: refused, nothing was sent; 1: the device or the line failed.
    """
    err.print(f"[bold red]error:[/] {escape(str(exc))}")
    return typer.Exit(code=code)


ConfigOption = Annotated[
    Path | None,
    typer.Option("--config", "-c", help="The gateway's YAML config (with --device)."),
]
DeviceOption = Annotated[
    str | None, typer.Option("--device", "-d", help="A device name from --config.")
]
PortOption = Annotated[
    str | None, typer.Option(help="Serial device or socket://HOST:PORT (without --config).")
]
AddressOption = Annotated[
    int | None, typer.Option(help="Device address 1..247 (without --config).", min=1, max=247)
]
ProfileOption = Annotated[
    str | None, typer.Option(help="Profile id, see 'gateway profiles' (without --config).")
]
BaudrateOption = Annotated[int, typer.Option(help="Line speed (without --config).")]
ParityOption = Annotated[str, typer.Option(help="N, E or O (without --config).")]
StopbitsOption = Annotated[int, typer.Option(help="1 or 2 (without --config).")]
TimeoutOption = Annotated[
    float | None, typer.Option(help="Response timeout in seconds (default: from the profile).")
]
FloatOrderOption = Annotated[
    str | None, typer.Option(help="ABCD, CDAB, BADC or DCBA (default: the device's).")
]


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceSpec:
    """Everything needed to open one device's line from the command line."""

    port: str
    line: LineFormat
    target: DeviceTarget
    policy: FlashPolicy  # the configured allow-list, or none without --config
    options: PortOptions = field(default_factory=PortOptions)  # the configured bus's
    state_dir: Path  # where the flash-write ledger is kept
    echo: EchoMode = EchoMode.AUTO  # the bus's echo setting
    tcp: TcpSettings | None = None  # the bus's tcp: settings (socket:// and tcp:// ports)
    # The config's clock.trust_unsynchronised (None without --config: the environment's).
    trust_unsynchronised: bool | None = None

    def clock(self) -> HostClock:
        """The host clock the command's writes of a date are gated by (as the gateway's)."""
        return HostClock(trust_unsynchronised=self.trust_unsynchronised)

    def ledger(self) -> FlashLedger:
        """The persistent flash-write ledger, shared with the running gateway."""
        return FlashLedger(self.state_dir / LEDGER_FILE)

    def records(self) -> RecordStore:
        """The record store, shared with the running gateway: every write goes in it."""
        return RecordStore(records_path(self.state_dir), clock_synchronised=self._synchronised)

    def _synchronised(self) -> bool:
        return self.clock().status().synchronised


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceOptions:
    """The device options as given on the command line, before they are resolved."""

    config: Path | None = None
    device: str | None = None
    port: str | None = None
    address: int | None = None
    profile: str | None = None
    baudrate: int = 9600
    parity: str = "N"
    stopbits: int = 1
    timeout: float | None = None
    float_order: str | None = None

    def spec(self) -> DeviceSpec:
        """The device they name (see :func:`device_spec`)."""
        return device_spec(self)


# The options in the order --help lists them, with their annotations and defaults.
_OPTIONS: tuple[tuple[str, object, object], ...] = (
    ("config", ConfigOption, None),
    ("device", DeviceOption, None),
    ("port", PortOption, None),
    ("address", AddressOption, None),
    ("profile", ProfileOption, None),
    ("baudrate", BaudrateOption, 9600),
    ("parity", ParityOption, "N"),
    ("stopbits", StopbitsOption, 1),
    ("timeout", TimeoutOption, None),
    ("float_order", FloatOrderOption, None),
)


def with_device_options(command: Callable[..., _R]) -> Callable[..., _R]:
    """Give a typer command the device options; it receives them as ``options``.

    Typer takes a command's options from its signature, so without this every command
    that acts on one sensor would spell out the same ten parameters. The wrapper's
    signature is the command's own (less ``options``) followed by the device options.
    """
    signature = inspect.signature(command)
    # Typer needs the annotations themselves (what Annotated holds), not their text;
    # ``options`` is typically annotated with a name imported only for type checking.
    hints = get_type_hints(command, localns={"DeviceOptions": DeviceOptions}, include_extras=True)
    own = [
        p.replace(annotation=hints.get(p.name, p.annotation))
        for p in signature.parameters.values()
        if p.name != "options"
    ]
    added = [
        inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=kind, default=default)
        for name, kind, default in _OPTIONS
    ]
    names = [name for name, _, _ in _OPTIONS]

    @functools.wraps(command)
    def wrapper(**kwargs: Any) -> _R:  # noqa: ANN401 - whatever typer parsed
        options = DeviceOptions(**{name: kwargs.pop(name) for name in names})
        return command(options=options, **kwargs)

    parameters = [*own, *added]
    wrapper.__signature__ = signature.replace(parameters=parameters)  # type: ignore[attr-defined]
    wrapper.__annotations__ = {p.name: p.annotation for p in parameters}
    return wrapper


def device_spec(options: DeviceOptions) -> DeviceSpec:
    """Resolve the options to one device, or a :class:`ConfigError` saying what is missing."""
    order = _word_order(options.float_order)
    if options.config is not None:
        if options.device is None:
            raise ConfigError("--config needs --device NAME")
        if options.port is not None or options.address is not None or options.profile is not None:
            raise ConfigError("give either --config with --device, or --port/--address/--profile")
        settings = load_config(options.config)
        found = [d for d in settings.devices if d.name == options.device]
        if not found:
            known = ", ".join(d.name for d in settings.devices) or "none"
            raise ConfigError(
                f"--device {options.device!r}: not in {options.config} (devices: {known})"
            )
        chosen = found[0]
        bus = settings.bus(chosen.bus)
        target = device_target(chosen, bus)
        target = DeviceTarget(
            name=target.name,
            address=target.address,
            profile=target.profile,
            intervals={},  # nothing is polled: the command reads what it needs
            float_order=order or target.float_order,
            timeout_s=options.timeout if options.timeout is not None else target.timeout_s,
            min_response_time_s=target.min_response_time_s,
            extra_gap_s=target.extra_gap_s,
            retries=target.retries,
            offline_after=target.offline_after,
        )
        return DeviceSpec(
            port=bus.port,
            line=bus.line,
            options=port_options(bus, settings.shared_bus),
            target=target,
            policy=chosen.flash_policy(),
            state_dir=state_directory(settings),
            echo=bus.echo,
            tcp=bus.tcp,
            trust_unsynchronised=settings.clock.trust_unsynchronised or None,
        )
    if options.port is None or options.address is None or options.profile is None:
        raise ConfigError("give --port, --address and --profile (or --config with --device)")
    if options.parity not in {"N", "E", "O"} or options.stopbits not in {1, 2}:
        raise ConfigError("--parity must be N, E or O and --stopbits 1 or 2")
    target = DeviceTarget(
        name=f"address_{options.address}",
        address=options.address,
        profile=get_profile(options.profile),
        intervals={},
        float_order=order,
        timeout_s=options.timeout,
    )
    return DeviceSpec(
        port=options.port,
        line=LineFormat(
            baudrate=options.baudrate,
            parity=options.parity,  # type: ignore[arg-type]  # checked above
            stopbits=options.stopbits,
        ),
        target=target,
        policy=FlashPolicy(allowed=frozenset(), daily_budget=DEFAULT_FLASH_WRITE_BUDGET),
        state_dir=Path("state"),
    )


def _word_order(text: str | None) -> codec.WordOrder | None:
    if text is None:
        return None
    try:
        return codec.WordOrder(text.upper())
    except ValueError:
        raise ConfigError(f"--float-order {text!r}: expected ABCD, CDAB, BADC or DCBA") from None


@contextlib.asynccontextmanager
async def device_link(spec: DeviceSpec) -> AsyncIterator[DeviceLink]:
    """Open the device's port and yield a link to it; the port is closed afterwards."""
    async with open_link(
        spec.port, spec.line, spec.target, echo=spec.echo, options=spec.options, tcp=spec.tcp
    ) as link:
        yield link
