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
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console

from gateway import codec
from gateway.app import device_target, state_directory
from gateway.config import DEFAULT_FLASH_WRITE_BUDGET, load_config
from gateway.errors import ConfigError, GatewayError
from gateway.flash import LEDGER_FILE, FlashLedger, FlashPolicy
from gateway.link import DeviceLink, open_link
from gateway.profiles import get_profile
from gateway.scheduler import DeviceTarget
from gateway.timing import LineFormat

if TYPE_CHECKING:
    from collections.abc import AsyncIterator


out = Console(highlight=False, soft_wrap=True)
err = Console(stderr=True, highlight=False)


def fail(exc: GatewayError) -> typer.Exit:
    """Print an error as the command line does everywhere; raise what it returns."""
    err.print(f"[bold red]error:[/] {exc}")
    return typer.Exit(code=2)


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
    state_dir: Path  # where the flash-write ledger is kept

    def ledger(self) -> FlashLedger:
        """The persistent flash-write ledger, shared with the running gateway."""
        return FlashLedger(self.state_dir / LEDGER_FILE)


def device_spec(
    *,
    config: Path | None,
    device: str | None,
    port: str | None,
    address: int | None,
    profile: str | None,
    baudrate: int = 9600,
    parity: str = "N",
    stopbits: int = 1,
    timeout: float | None = None,
    float_order: str | None = None,
) -> DeviceSpec:
    """Resolve the options to one device, or a :class:`ConfigError` saying what is missing."""
    order = _word_order(float_order)
    if config is not None:
        if device is None:
            raise ConfigError("--config needs --device NAME")
        if port is not None or address is not None or profile is not None:
            raise ConfigError("give either --config with --device, or --port/--address/--profile")
        settings = load_config(config)
        found = [d for d in settings.devices if d.name == device]
        if not found:
            known = ", ".join(d.name for d in settings.devices) or "none"
            raise ConfigError(f"--device {device!r}: not in {config} (devices: {known})")
        chosen = found[0]
        bus = settings.bus(chosen.bus)
        target = device_target(chosen, bus)
        target = DeviceTarget(
            name=target.name,
            address=target.address,
            profile=target.profile,
            intervals={},  # nothing is polled: the command reads what it needs
            float_order=order or target.float_order,
            timeout_s=timeout if timeout is not None else target.timeout_s,
            min_response_time_s=target.min_response_time_s,
            extra_gap_s=target.extra_gap_s,
            retries=target.retries,
            offline_after=target.offline_after,
        )
        return DeviceSpec(
            port=bus.port,
            line=bus.line,
            target=target,
            policy=chosen.flash_policy(),
            state_dir=state_directory(settings),
        )
    if port is None or address is None or profile is None:
        raise ConfigError("give --port, --address and --profile (or --config with --device)")
    if parity not in {"N", "E", "O"} or stopbits not in {1, 2}:
        raise ConfigError("--parity must be N, E or O and --stopbits 1 or 2")
    target = DeviceTarget(
        name=f"address_{address}",
        address=address,
        profile=get_profile(profile),
        intervals={},
        float_order=order,
        timeout_s=timeout,
    )
    return DeviceSpec(
        port=port,
        line=LineFormat(baudrate=baudrate, parity=parity, stopbits=stopbits),  # type: ignore[arg-type]
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
    async with open_link(spec.port, spec.line, spec.target) as link:
        yield link
