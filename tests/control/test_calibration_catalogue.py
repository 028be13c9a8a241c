"""The calibration catalogue, and the front ends that read it.

Pure tests of :mod:`gateway.control.calibration.catalogue` (which device offers what, the
defaults and where they come from, the checks of what a front end was given), then one test
that the command line, the web page and MQTT offer every built-in profile the same
procedures with the same defaults: the real gateway with its page and its MQTT commands on
a simulated line with one sensor of each profile, a real mosquitto, and the command line's
own commands through typer's runner; and the defaults as the page applies them to a run.
"""

from __future__ import annotations

import asyncio
import inspect
import json
from typing import TYPE_CHECKING, Any

import aiohttp
import aiomqtt
import pytest
import typer
from typer.testing import CliRunner

from gateway.care.rules import CALIBRATION_PROCEDURE, CareKind
from gateway.cli.calibrate import calibrate_app
from gateway.cli.root import app as gateway_app
from gateway.control.calibration import (
    calibrate_oxygen_end_value,
    calibrate_oxygen_zero,
    calibrate_slope,
    calibrate_zero_point,
    catalogue,
    check_slope,
)
from gateway.errors import CommandRejectedError
from gateway.profiles import builtin_profiles, get_profile
from tests.mqtt_broker import free_port, recording
from tests.publish.test_mqtt import gateway, simulated

if TYPE_CHECKING:
    from collections.abc import Callable
    from pathlib import Path

    from tests.mqtt_broker import Broker

CL2 = get_profile("jumo-tecline-cl2")
H10 = get_profile("jumo-digiline-odo-h10")
S10 = get_profile("jumo-digiline-odo-s10")

# What each family's manual describes: tecLine annex 7 and Reiss chapter 5 (slope, zero
# point, nominal slope, the regular check); H10/H20 manual 6.2.4 (zero point, end value);
# the S10's Modbus manual has no calibration procedure.
BY_FAMILY = {
    "jumo-tecline": ["slope", "zero", "nominal", "check"],
    "reiss-m0c-m3c": ["slope", "zero", "nominal", "check"],
    "jumo-digiline-odo-h10-h20": ["oxygen_zero", "oxygen_end_value"],
    "jumo-digiline-odo-s10": [],
}


# --- the catalogue, pure --------------------------------------------------------------------


def test_each_built_in_profile_offers_its_manuals_procedures() -> None:
    for profile_id, profile in builtin_profiles().items():
        offered = [p.id for p in catalogue.offered(profile)]
        assert offered == BY_FAMILY[profile.family], profile_id
        for procedure in catalogue.PROCEDURES:
            assert (profile_id in catalogue.offering(procedure)) == (procedure.id in offered)


def test_ids_are_unique_and_every_command_runs_one_procedure_per_device() -> None:
    assert len(catalogue.BY_ID) == len(catalogue.PROCEDURES)
    assert catalogue.COMMANDS == ("slope", "zero", "nominal", "check", "end-value")
    for profile in builtin_profiles().values():
        for command in catalogue.COMMANDS:
            mine = [p for p in catalogue.offered(profile) if p.command == command]
            assert len(mine) <= 1, (profile.id, command)


def test_the_defaults_are_the_manuals_one_reading_once_the_signal_is_stable() -> None:
    # tecLine annex 7.3.1 steps 2-3 / 7.4.1 steps 2-3, Reiss 5.2.1: read once and note it.
    for procedure_id in ("slope", "zero", "check"):
        defaults = catalogue.procedure(procedure_id).defaults()
        assert defaults.integer("samples") == 1
        assert defaults.number("every") == 1.0
        sources = {p.name: p.source for p in catalogue.procedure(procedure_id).parameters}
        assert "7.3.1 steps 2-3" in sources["samples"]
        assert "Reiss 5.2.1" in sources["samples"]
        assert sources["every"].startswith("ours:")  # the manuals give no interval
    # H10/H20 manual 6.2.4: 0x3009 is 0 at start-up, the mode configured at 0x2021.
    assert catalogue.procedure("oxygen_zero").defaults().text("mode") == "as_configured"
    assert catalogue.procedure("oxygen_end_value").defaults().optional_text("unit") is None


def test_every_parameter_has_a_source_and_a_default_within_its_bounds() -> None:
    for procedure in catalogue.PROCEDURES:
        assert procedure.source
        assert procedure.needs
        for parameter in procedure.parameters:
            assert parameter.source, (procedure.id, parameter.name)
            assert parameter.option == "--" + parameter.name.replace("_", "-")
            if parameter.required:
                assert parameter.default is None
                continue
            if parameter.default is None:  # left out, it means something: say what
                assert parameter.absent, (procedure.id, parameter.name)
            if parameter.default is not None:  # a default passes its own checks
                assert parameter.parse(parameter.default) == parameter.default
            assert parameter.parse("") == parameter.default  # a blank field is the default


def test_the_flows_keyword_defaults_are_the_catalogues() -> None:
    """One set of defaults: a flow called without an input does what the catalogue says."""
    flows: dict[str, Callable[..., object]] = {
        "slope": calibrate_slope,
        "zero": calibrate_zero_point,
        "check": check_slope,
        "oxygen_zero": calibrate_oxygen_zero,
        "oxygen_end_value": calibrate_oxygen_end_value,
    }
    keyword = {"samples": "samples", "every": "sample_interval_s", "mode": "mode"}
    for procedure_id, flow in flows.items():
        signature = inspect.signature(flow)
        for parameter in catalogue.procedure(procedure_id).parameters:
            name = keyword.get(parameter.name)
            if name is not None:
                assert signature.parameters[name].default == parameter.default, (
                    procedure_id,
                    name,
                )


def test_the_choices_are_the_profiles_labels() -> None:
    modes = H10.point("calibration_mode").format.enum
    assert catalogue.MODE.choices == tuple(modes[code] for code in sorted(modes))
    units = H10.point("end_value_oxygen_unit").format.enum
    assert set(catalogue.UNIT.choices) == set(units.values())


def test_inputs_from_a_form_are_checked_and_defaulted() -> None:
    slope = catalogue.procedure("slope")
    inputs = slope.parse({"reference": " 0.52 ", "cell_current": "", "samples": "3"})
    assert inputs.number("reference") == 0.52
    assert inputs.optional_number("cell_current") is None
    assert inputs.integer("samples") == 3
    assert inputs.number("every") == 1.0
    refused: list[tuple[dict[str, object], str]] = [
        ({}, "reference is required"),
        ({"reference": "x"}, "reference: 'x' is not a number"),
        ({"reference": "nan"}, "is not a number"),
        ({"reference": True}, "is not a number"),
        ({"reference": 1, "samples": "0"}, "samples must be a whole number from 1 to 100, got '0'"),
        ({"reference": 1, "samples": 2.5}, "samples must be a whole number"),
        ({"reference": 1, "every": "61"}, "every must be a number from 0 to 60 s"),
        ({"reference": 1, "mode": "wet"}, "the slope calibration takes no mode"),
    ]
    for given, message in refused:
        with pytest.raises(CommandRejectedError, match=message):
            slope.parse(given)
    end_value = catalogue.procedure("oxygen_end_value")
    assert end_value.parse({"reference": "20.9", "unit": ""}).optional_text("unit") is None
    with pytest.raises(CommandRejectedError, match="mode must be one of as_configured, wet, dry"):
        end_value.parse({"reference": "20.9", "mode": "damp"})
    assert catalogue.procedure("nominal").parse({}).values == {}


def test_one_command_for_two_procedures_picks_the_devices_own() -> None:
    given = {"zero_current": None, "samples": 1, "every": 1.0, "mode": "as_configured"}
    chosen, inputs = catalogue.choose("zero", H10, given, device="d")
    assert chosen.id == "oxygen_zero"
    assert dict(inputs.values) == {"mode": "as_configured"}  # the others were defaults
    chosen, inputs = catalogue.choose("zero", CL2, given, device="d")
    assert chosen.id == "zero"
    assert dict(inputs.values) == {"zero_current": None, "samples": 1, "every": 1.0}
    with pytest.raises(CommandRejectedError, match="--mode is for the H10/H20 zero-point"):
        catalogue.choose("zero", CL2, {**given, "mode": "wet"}, device="d")
    with pytest.raises(CommandRejectedError, match="--samples is for the tecLine/Reiss"):
        catalogue.choose("zero", H10, {**given, "samples": 5}, device="d")
    with pytest.raises(
        CommandRejectedError,
        match=r"d \(jumo-digiline-odo-s10\) has no zero-point calibration: that is for "
        r"tecLine/Reiss or H10/H20 sensors \(this device has no guided calibration\)",
    ):
        catalogue.choose("zero", S10, given, device="d")
    with pytest.raises(
        CommandRejectedError, match=r"has no slope calibration.*zero \(oxygen_zero\)"
    ):
        catalogue.choose("slope", H10, {"reference": 1.0}, device="d")


def test_care_asks_for_a_procedure_the_catalogue_has() -> None:
    assert set(CALIBRATION_PROCEDURE.values()) <= set(catalogue.BY_ID)
    assert set(CALIBRATION_PROCEDURE) == {CareKind.AMPEROMETRIC, CareKind.OPTICAL_HYGIENIC}
    asked = catalogue.asked_by_care(CL2)
    assert asked is not None
    assert asked.id == "slope"
    asked = catalogue.asked_by_care(H10)
    assert asked is not None
    assert asked.id == "oxygen_end_value"
    assert catalogue.asked_by_care(S10) is None


def test_a_procedure_is_json_ready() -> None:
    for procedure in catalogue.PROCEDURES:
        document = json.loads(json.dumps(procedure.as_dict()))
        assert document["id"] == procedure.id
        assert [f["name"] for f in document["fields"]] == [p.name for p in procedure.parameters]


# --- the front ends -------------------------------------------------------------------------

PASSWORD = "correct horse battery"  # noqa: S105 - the test gateway's
PROFILES = sorted(builtin_profiles())
ADDRESSES = {profile_id: n for n, profile_id in enumerate(PROFILES, start=1)}
SENSORS: list[dict[str, Any]] = [
    {"profile": profile_id, "address": address, "animate": False}
    for profile_id, address in ADDRESSES.items()
]


def _name(profile_id: str) -> str:
    return profile_id.replace("-", "_")


def _config(tmp_path: Path, broker: int, web: int) -> str:
    devices = "".join(
        f"  - {{name: {_name(pid)}, bus: line1, address: {address}, profile: {pid},"
        " poll_interval: 2}\n"
        for pid, address in ADDRESSES.items()
    )
    return (
        f"buses:\n  - {{name: line1, port: {tmp_path / 'ttySIM'}}}\n"
        f"devices:\n{devices}"
        f"mqtt: {{host: 127.0.0.1, port: {broker}, base_topic: gw, reconnect_max_s: 1}}\n"
        "prometheus: {enabled: false}\n"
        f"web: {{enabled: true, port: {web}, password: {json.dumps(PASSWORD)}}}\n"
        f"state_dir: {tmp_path / 'state'}\n"
    )


async def _listening(port: int) -> None:
    for _ in range(200):
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
        except OSError:
            await asyncio.sleep(0.05)
            continue
        writer.close()
        await writer.wait_closed()
        return
    raise AssertionError(f"nothing listens on {port}")


def _cli_listing(profile_id: str) -> list[dict[str, Any]]:
    """``gateway calibrate procedures --profile ID --json``, through the command line."""
    result = CliRunner().invoke(
        gateway_app, ["calibrate", "procedures", "--profile", profile_id, "--json"]
    )
    assert result.exit_code == 0, result.output
    listing: list[dict[str, Any]] = json.loads(result.stdout)
    return listing


def _cli_options(command: str) -> dict[str, Any]:
    """The options of ``gateway calibrate COMMAND`` as typer built them, by name."""
    group = typer.main.get_group(calibrate_app)
    return {str(p.name): p for p in group.commands[command].params}


def _check_cli_options(procedure: catalogue.Procedure) -> None:
    """The command's options are the procedure's parameters, with its defaults and bounds."""
    options = _cli_options(procedure.command)
    for parameter in procedure.parameters:
        option = options[parameter.name]
        assert option.opts == [parameter.option], parameter.name
        assert option.default == parameter.default, (procedure.id, parameter.name)
        assert option.required == parameter.required, (procedure.id, parameter.name)
        bounds = (getattr(option, "min", None), getattr(option, "max", None))
        assert bounds == (parameter.minimum, parameter.maximum), parameter.name


@pytest.mark.line
@pytest.mark.broker
async def test_the_command_line_the_page_and_mqtt_offer_the_same_procedures_and_defaults(
    tmp_path: Path, broker: Broker
) -> None:
    web = free_port()
    async with (
        simulated(tmp_path, SENSORS),
        recording(broker.port, "gw/+/command/#") as seen,
        gateway(_config(tmp_path, broker.port, web)),
        aiohttp.ClientSession() as http,
    ):
        await _listening(web)
        async with aiomqtt.Client("127.0.0.1", broker.port) as client:
            for profile_id in PROFILES:
                device = _name(profile_id)
                expected = [p.as_dict() for p in catalogue.offered(get_profile(profile_id))]
                url = f"http://127.0.0.1:{web}/api/devices/{device}"
                async with http.get(url) as response:
                    assert response.status == 200
                    page = (await response.json())["procedures"]
                topic = f"gw/{device}/command/calibrations"
                before = len(seen.on(f"{topic}/result"))
                await client.publish(topic, '{"id": "c1"}', qos=1)
                await seen.wait_for(f"{topic}/result", skip=before, within_s=15)
                mqtt = json.loads(seen.on(f"{topic}/result")[before])
                cli = _cli_listing(profile_id)

                assert page == expected, profile_id
                assert cli == expected, profile_id
                if expected:
                    assert mqtt["status"] == "ok", mqtt
                    assert mqtt["result"]["procedures"] == expected, profile_id
                    assert "does not start them" in mqtt["result"]["note"]
                else:  # the S10: nothing to list, and MQTT says so
                    assert mqtt["status"] == "error", mqtt
                    assert "'calibrations' does not apply" in mqtt["reason"]
                for procedure in catalogue.offered(get_profile(profile_id)):
                    _check_cli_options(procedure)


@pytest.mark.line
@pytest.mark.broker
async def test_the_page_applies_the_catalogues_defaults_to_a_run(
    tmp_path: Path, broker: Broker
) -> None:
    """A check started with the reference alone reads the cell current as often as the
    catalogue says (the command line's twin is in ``tests/cli/test_cli_calibrate.py``)."""
    web = free_port()
    device = _name("jumo-tecline-cl2")
    jar = aiohttp.CookieJar(unsafe=True)  # the session cookie of 127.0.0.1
    async with (
        simulated(tmp_path, SENSORS),
        gateway(_config(tmp_path, broker.port, web)),
        aiohttp.ClientSession(f"http://127.0.0.1:{web}", cookie_jar=jar) as http,
    ):
        await _listening(web)
        async with http.post("/api/login", json={"name": "ana", "password": PASSWORD}) as r:
            assert r.status == 200
        async with http.get("/api/session") as r:
            csrf = (await r.json())["csrf"]
        body = {
            "device": device,
            "procedure": "check",
            "inputs": {"reference": "0.5"},
            "password": PASSWORD,  # the start is signed
        }
        async with http.post("/api/calibrations", json=body, headers={"X-CSRF-Token": csrf}) as r:
            assert r.status == 201, await r.text()
            run_id = (await r.json())["id"]
        for _ in range(300):
            async with http.get(f"/api/calibrations/{run_id}") as r:
                run = await r.json()
            if run["phase"] not in {"running", "confirm", "writing"}:
                break
            await asyncio.sleep(0.1)
    assert run["phase"] == "done", run
    assert run["outcome"]["status"] == "checked"
    readings = run["outcome"]["values"]["cell_current_samples"]
    assert len(readings) == catalogue.procedure("check").defaults().integer("samples") == 1
    assert run["outcome"]["writes"] == []
