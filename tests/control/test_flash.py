"""Flash-wear protection: the per-device allow list, the daily budget, the ledger."""

from __future__ import annotations

from datetime import date
from pathlib import Path

import pytest

from gateway.config import FlashPolicy
from gateway.control.commands import validate_write, writable_point
from gateway.control.flash import Action, Decision, FlashLedger, check_flash_write
from gateway.errors import CommandRejectedError, ConfigError
from gateway.profiles import get_profile
from gateway.profiles.model import Profile
from gateway.wire.codec import WordOrder

DAY = date(2025, 2, 10)
NEXT_DAY = date(2025, 2, 11)


@pytest.fixture
def ledger(tmp_path: Path) -> FlashLedger:
    return FlashLedger(tmp_path / "state" / "flash.sqlite")


@pytest.fixture(scope="module")
def tecline() -> Profile:
    return get_profile("jumo-tecline-cl2")


def span(value: float) -> tuple[int, ...]:
    return validate_write(
        get_profile("jumo-tecline-cl2"),
        writable_point(get_profile("jumo-tecline-cl2"), "x_span"),
        value,
        float_order=WordOrder.CDAB,
    )


def check(
    profile: Profile,
    point: str,
    *,
    ledger: FlashLedger,
    policy: FlashPolicy,
    registers: tuple[int, ...],
    current: tuple[int, ...] | None = None,
    today: date = DAY,
) -> Decision:
    return check_flash_write(
        writable_point(profile, point),
        "pool",
        policy=policy,
        ledger=ledger,
        current=current,
        registers=registers,
        today=today,
    )


ALLOW_SPAN = FlashPolicy(allowed=frozenset({"x_span", "description"}), daily_budget=2)


def test_flash_point_not_allowed(tecline: Profile, ledger: FlashLedger) -> None:
    decision = check(
        tecline,
        "x_span",
        ledger=ledger,
        policy=FlashPolicy(allowed=frozenset(), daily_budget=5),
        registers=span(2.0),
    )
    assert decision.action is Action.REFUSE
    assert decision.reason == (
        "flash-backed point not allowed for device pool (add it to the device's flash_writes)"
    )


def test_ram_and_volatile_points_are_free(ledger: FlashLedger) -> None:
    nothing = FlashPolicy(allowed=frozenset(), daily_budget=0)
    s10 = get_profile("jumo-digiline-odo-s10")
    h10 = get_profile("jumo-digiline-odo-h10")
    for profile, point, registers in [
        (s10, "compensation_temperature", (0x0000, 0x41A2)),
        (h10, "calibration_mode", (1,)),
    ]:
        decision = check(
            profile, point, ledger=ledger, policy=nothing, registers=registers, current=registers
        )
        assert decision == Decision(action=Action.WRITE)
        assert not decision.record
    assert ledger.totals() == {}


def test_budget_is_spent_then_renews_the_next_day(tecline: Profile, ledger: FlashLedger) -> None:
    for value in (2.0, 3.0):
        decision = check(tecline, "x_span", ledger=ledger, policy=ALLOW_SPAN, registers=span(value))
        assert decision == Decision(action=Action.WRITE, record=True)
        ledger.record("pool", "x_span", DAY)
    decision = check(tecline, "x_span", ledger=ledger, policy=ALLOW_SPAN, registers=span(4.0))
    assert decision.action is Action.REFUSE
    assert decision.reason == "budget of 2 writes per day for pool/x_span is spent"
    tomorrow = check(
        tecline, "x_span", ledger=ledger, policy=ALLOW_SPAN, registers=span(4.0), today=NEXT_DAY
    )
    assert tomorrow.action is Action.WRITE


def test_unchanged_value_is_skipped_and_not_counted(tecline: Profile, ledger: FlashLedger) -> None:
    decision = check(
        tecline, "x_span", ledger=ledger, policy=ALLOW_SPAN, registers=span(2.0), current=span(2.0)
    )
    assert decision == Decision(action=Action.SKIP, reason="unchanged, not written")
    changed = check(
        tecline, "x_span", ledger=ledger, policy=ALLOW_SPAN, registers=span(2.0), current=span(2.5)
    )
    assert changed.action is Action.WRITE


def test_unchanged_string_compares_up_to_its_terminator(ledger: FlashLedger) -> None:
    s10 = get_profile("jumo-digiline-odo-s10")
    text = validate_write(
        s10, writable_point(s10, "description"), "Anlage Nord", float_order=WordOrder.CDAB
    )
    read = text + (0,) * (96 - len(text))
    decision = check(
        s10, "description", ledger=ledger, policy=ALLOW_SPAN, registers=text, current=read
    )
    assert decision.action is Action.SKIP
    other = validate_write(
        s10, writable_point(s10, "description"), "Anlage", float_order=WordOrder.CDAB
    )
    assert (
        check(
            s10, "description", ledger=ledger, policy=ALLOW_SPAN, registers=other, current=read
        ).action
        is Action.WRITE
    )


def test_a_zero_budget_refuses_every_flash_write(tecline: Profile, ledger: FlashLedger) -> None:
    policy = FlashPolicy(allowed=frozenset({"x_span"}), daily_budget=0)
    assert (
        check(tecline, "x_span", ledger=ledger, policy=policy, registers=span(2.0)).action
        is Action.REFUSE
    )


def test_negative_budget_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="0 or more"):
        FlashPolicy(allowed=frozenset(), daily_budget=-1)


def test_read_only_and_unknown_points_are_rejected(tecline: Profile, ledger: FlashLedger) -> None:
    with pytest.raises(CommandRejectedError, match="no point 'nope'"):
        check(tecline, "nope", ledger=ledger, policy=ALLOW_SPAN, registers=(1,))


def test_ledger_counts_per_day_and_survives_reopening(tmp_path: Path) -> None:
    path = tmp_path / "flash.sqlite"
    ledger = FlashLedger(path)
    ledger.record("pool", "x_span", DAY)
    ledger.record("pool", "x_span", DAY)
    ledger.record("pool", "x_span", NEXT_DAY)
    ledger.record("tank", "description", DAY)
    ledger.close()
    reopened = FlashLedger(path)
    assert reopened.count_today("pool", "x_span", DAY) == 2
    assert reopened.count_today("pool", "x_span", NEXT_DAY) == 1
    assert reopened.count_today("pool", "x_span", date(2025, 2, 12)) == 0
    assert reopened.total("pool", "x_span") == 3
    assert reopened.total("pool", "nothing") == 0
    assert reopened.totals() == {("pool", "x_span"): 3, ("tank", "description"): 1}
    reopened.close()


def test_unwritable_ledger_path_is_a_clear_config_error(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("a file where the state directory should be")
    with pytest.raises(ConfigError, match=r"flash-write ledger .* cannot be written"):
        FlashLedger(blocker / "flash.sqlite")


def test_a_failed_record_rejects_the_command(tmp_path: Path) -> None:
    ledger = FlashLedger(tmp_path / "flash.sqlite")
    ledger._connection().execute("DROP TABLE flash_writes")  # the file lost its table under us
    with pytest.raises(CommandRejectedError, match="cannot be counted"):
        ledger.record("pool", "x_span", DAY)
    ledger.close()
