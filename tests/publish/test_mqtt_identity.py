"""The owner marker's verdicts and the server walk, without a broker (the broker tests are in
tests/publish/test_mqtt_servers.py)."""

from __future__ import annotations

import json

import pytest

from gateway.config import MqttConfig, MqttServer
from gateway.publish.mqtt.identity import Claim, IdentityGuard, IdentityTakenError
from gateway.publish.mqtt.servers import ServerWalk


def first_connection(guard: IdentityGuard) -> Claim:
    """The claim a connection publishes, as another gateway reads it."""
    claim = Claim.parse(guard.claim().payload)
    assert claim is not None
    return claim


def test_a_claim_is_retained_json_with_who_and_since() -> None:
    guard = IdentityGuard("plant/cab1", "gateway-cab1", start_id="a1")
    message = guard.claim()
    assert (message.topic, message.qos, message.retain) == ("plant/cab1/owner", 1, True)
    data = json.loads(message.payload)
    assert data["start_id"] == "a1"
    assert data["client_id"] == "gateway-cab1"
    assert isinstance(data["pid"], int)
    assert "contested_by" not in data
    assert Claim.parse(b"") is None  # a cleared marker
    assert Claim.parse(b"online") is None


def test_the_newcomer_stands_down_and_the_holder_is_untouched() -> None:
    holder = IdentityGuard("gw", "gateway-x", start_id="a1")
    newcomer = IdentityGuard("gw", "gateway-x", start_id="b2")
    held = first_connection(holder)
    claimed = first_connection(newcomer)
    # The newcomer reads the holder's retained claim at its first connection: it may be a
    # dead run's, so it claims and waits for an answer.
    assert newcomer.judge(held.payload(), retained=True) == []
    # The holder reads the newcomer's claim live (or retained when it reconnects): it defends.
    defence = holder.judge(claimed.payload(), retained=False)
    marker, status = defence
    assert (marker.topic, marker.retain) == ("gw/owner", True)
    assert json.loads(marker.payload)["contested_by"] == "b2"
    assert (status.topic, status.payload, status.retain) == ("gw/status", b"online", True)
    # The newcomer reads the defence naming it: it stands down, saying who holds it.
    with pytest.raises(IdentityTakenError, match="gateway-x") as taken:
        newcomer.judge(marker.payload, retained=False)
    assert "mqtt.base_topic" in str(taken.value)
    # Its own claim echoed back is nothing; the holder stays.
    assert holder.judge(held.payload(), retained=False) == []


def test_a_will_saying_offline_while_connected_is_answered_online() -> None:
    guard = IdentityGuard("gw", "gateway-x", start_id="a1")
    first_connection(guard)
    # Retained, at the subscription: the last run's word, before this session's online.
    assert guard.answer_status(b"offline", retained=True) == []
    assert guard.answer_status(b"online", retained=False) == []
    (answer,) = guard.answer_status(b"offline", retained=False)  # another client's will
    assert (answer.topic, answer.payload, answer.qos, answer.retain) == (
        "gw/status",
        b"online",
        1,
        True,
    )


def test_a_claim_awaits_an_answer_only_where_the_marker_named_another_run() -> None:
    holder = IdentityGuard("gw", "gateway-x", start_id="a1")
    held = first_connection(holder)
    # A broker without a marker: the claim comes back, nobody could answer.
    assert holder.judge(held.payload(), retained=False) == []
    assert holder.echoed
    assert not holder.answer_awaited
    # A newcomer reads the holder's marker (retained) before its own claim comes back.
    newcomer = IdentityGuard("gw", "gateway-x", start_id="b2")
    claimed = first_connection(newcomer)
    assert newcomer.judge(held.payload(), retained=True) == []
    assert not newcomer.echoed
    assert newcomer.judge(claimed.payload(), retained=False) == []
    assert newcomer.echoed
    assert newcomer.answer_awaited
    # Thrown off before its wait ended (the holder came back with the same client id): at
    # the next connection the claim has not stood, the holder's marker is yielded to again.
    first_connection(newcomer)
    assert not newcomer.echoed
    assert not newcomer.answer_awaited  # nothing read yet in this session
    assert newcomer.judge(held.payload(), retained=True) == []
    assert newcomer.answer_awaited
    # Its wait ended unanswered: the claim stands, nothing is awaited at later connections.
    newcomer.has_stood()
    first_connection(newcomer)
    assert newcomer.judge(held.payload(), retained=True) != []  # defended, not yielded to
    assert not newcomer.answer_awaited


def test_a_claim_read_retained_at_a_reconnection_is_defended() -> None:
    holder = IdentityGuard("gw", "gateway-x", start_id="a1")
    first_connection(holder)
    holder.has_stood()
    first_connection(holder)  # thrown off by a newcomer with the same client id: back again
    other = Claim(start_id="b2", client_id="gateway-x", host="h", pid=1, since="s")
    assert len(holder.judge(other.payload(), retained=True)) == 2


def test_a_dead_runs_marker_is_replaced_without_a_fight() -> None:
    dead = IdentityGuard("gw", "gateway-x", start_id="a1")
    restarted = IdentityGuard("gw", "gateway-x", start_id="c3")
    first_connection(restarted)
    assert restarted.judge(first_connection(dead).payload(), retained=True) == []


def test_two_claims_at_once_the_larger_start_id_stands_down() -> None:
    small = IdentityGuard("gw", "a", start_id="1111")
    large = IdentityGuard("gw", "b", start_id="9999")
    small_claim, large_claim = first_connection(small), first_connection(large)
    (small_defence, _) = small.judge(large_claim.payload(), retained=False)
    (large_defence, _) = large.judge(small_claim.payload(), retained=False)
    assert small.judge(large_defence.payload, retained=False) == []  # the smaller one stays
    with pytest.raises(IdentityTakenError):
        large.judge(small_defence.payload, retained=False)


def servers(*hosts: str) -> list[MqttServer]:
    return [MqttServer(host=h) for h in hosts]


def test_the_walk_moves_on_at_each_failure_and_says_when_a_round_is_done() -> None:
    walk = ServerWalk(servers("a", "b", "c"), return_to_first_s=600)
    assert (walk.current.host, walk.stay_for()) == ("a", None)  # at home: no time limit
    assert walk.next() is False
    assert (walk.current.host, walk.stay_for()) == ("b", 600)
    assert walk.next() is False
    assert walk.next() is True  # a, b and c failed once: the backoff waits
    assert walk.current.host == "a"
    assert walk.switches == 3
    walk.next()
    walk.first()
    assert (walk.current.host, walk.switches) == ("a", 5)
    walk.first()
    assert walk.switches == 5  # staying is no switch


def test_one_server_is_a_round_at_every_failure() -> None:
    walk = ServerWalk(MqttConfig(host="broker", port=1884).server_list(), return_to_first_s=None)
    assert walk.current.address == "broker:1884"
    assert walk.several is False
    assert walk.next() is True
    assert walk.switches == 0
    stay = ServerWalk(servers("a", "b"), return_to_first_s=None)
    stay.next()
    assert stay.stay_for() is None  # return_to_first_s: null stays where it is
    with pytest.raises(ValueError, match="at least one"):
        ServerWalk([], return_to_first_s=None)


def test_an_ipv6_server_is_named_in_brackets() -> None:
    assert MqttServer(host="fd00::5", port=8883).address == "[fd00::5]:8883"
