"""Other masters' turns, without I/O: the share divided by bus time between their clients."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from gateway.line.engine.fair_share import ANTICIPATION_S, FairShare, Origin


@dataclass
class Job:
    origin: Origin
    queued_at: float
    bus_s: float = 0.0


def _serve(fair: FairShare, jobs: list[Job]) -> Job:
    job = fair.pick(jobs)
    assert job is not None
    jobs.remove(job)
    fair.charge(job.origin, job.bus_s, now=0.0)
    return job


GREEDY = Origin("10.0.0.5", "10.0.0.5:4000")
SCADA = Origin("10.0.0.7", "10.0.0.7:5000")


def test_the_client_that_had_less_bus_time_goes_next() -> None:
    fair = FairShare()
    served: list[Origin] = []
    jobs = [Job(GREEDY, queued_at=0.0, bus_s=0.29)]
    for n in range(60):  # both keep one request waiting, as a client reading in turn does
        if not any(j.origin == SCADA for j in jobs):
            jobs.append(Job(SCADA, queued_at=n, bus_s=0.029))
        if not any(j.origin == GREEDY for j in jobs):
            jobs.append(Job(GREEDY, queued_at=n, bus_s=0.29))
        served.append(_serve(fair, jobs).origin)
    # Ten short reads of the SCADA for each long one of the other: the same bus time.
    assert served.count(GREEDY) in {5, 6}
    assert served[:12] == [GREEDY] + [SCADA] * 10 + [GREEDY]


def test_a_client_that_asked_nothing_for_a_while_saved_nothing_up() -> None:
    fair = FairShare()
    for n in range(20):  # the greedy one alone: it may have it all meanwhile
        fair.charge(GREEDY, 0.29, now=n)
    jobs = [Job(GREEDY, queued_at=20.0, bus_s=0.29), Job(SCADA, queued_at=20.5, bus_s=0.29)]
    # The SCADA comes back: it goes first once (the other had the last), then they alternate.
    order = [_serve(fair, jobs).origin]
    jobs += [Job(SCADA, queued_at=21.0, bus_s=0.29)]
    order += [_serve(fair, jobs).origin for _ in range(2)]
    assert order == [SCADA, GREEDY, SCADA]


def test_an_address_gets_one_part_however_many_connections_it_opens() -> None:
    fair = FairShare()
    many = [Origin("10.0.0.5", f"10.0.0.5:{4000 + n}") for n in range(15)]
    jobs = [Job(origin, queued_at=0.0, bus_s=0.1) for origin in many]
    jobs.append(Job(SCADA, queued_at=1.0, bus_s=0.1))
    served: list[Origin] = []
    for n in range(40):
        job = _serve(fair, jobs)
        served.append(job.origin)
        jobs.append(Job(job.origin, queued_at=2.0 + n, bus_s=0.1))  # each asks again
    assert served.count(SCADA) == 20
    # Within the address, its connections in turn: each of the fifteen once, then again.
    assert [o for o in served if o != SCADA][:15] == many
    assert set([o for o in served if o != SCADA][15:20]) <= set(many)


def test_between_equals_the_request_waiting_longest_goes_first() -> None:
    fair = FairShare()
    first, second = Job(SCADA, queued_at=1.0), Job(GREEDY, queued_at=2.0)
    assert fair.pick([second, first]) is first
    assert fair.pick([]) is None


def test_the_turn_is_kept_for_a_client_asking_back_to_back_that_had_less() -> None:
    fair = FairShare()
    fair.charge(GREEDY, 0.29, now=10.0)
    fair.charge(SCADA, 0.029, now=10.5)  # answered; its next request is on its way
    greedy = Job(GREEDY, queued_at=10.2)
    assert fair.held_until(greedy, 10.5) == pytest.approx(10.5 + ANTICIPATION_S)
    assert fair.held_until(greedy, 10.6) == 10.6  # it did not come: the line is not kept
    # Kept only for one that had less: once the SCADA had more, the other's turn stands.
    for n in range(12):
        fair.charge(SCADA, 0.029, now=11.0 + n / 100)
    assert fair.held_until(greedy, 11.12) == 11.12


def test_a_full_queue_takes_the_newest_request_of_the_address_holding_most() -> None:
    fair = FairShare()
    many = [Origin("10.0.0.5", f"10.0.0.5:{4000 + n}") for n in range(8)]
    jobs = [Job(origin, queued_at=float(n)) for n, origin in enumerate(many)]
    assert fair.displaced(jobs, SCADA) is jobs[-1]
    assert fair.displaced(jobs, many[0]) is None  # its own address holds the most
    # Seven against one: still one to give; four against three (one apart) is even enough.
    mixed = [*jobs[:7], Job(SCADA, queued_at=9.0)]
    assert fair.displaced(mixed, SCADA) is mixed[6]
    even = [*jobs[:4], *(Job(SCADA, queued_at=9.0 + n) for n in range(3))]
    assert fair.displaced(even, SCADA) is None
    assert fair.displaced([], SCADA) is None
