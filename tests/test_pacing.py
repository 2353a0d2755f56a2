"""The simulation clock's pacing (``runtime.pacing``), on a wall clock of our own: what a step loop does
when it waits as told and steps when told to."""

from __future__ import annotations

import math

import pytest

from droneulator.runtime.pacing import Pacer

DT = 0.01  # one control period, sim s


def run(
    pacer: Pacer, sim_t: float, wall: float, until_wall: float, hold: tuple[float, float] | None = None
) -> list[tuple[float, float]]:
    """Step a clock of period DT as the pacer says from (sim_t, wall) until ``until_wall``; each step takes
    no wall time; ``hold``: (from, to) wall s in which no step may be taken (a frame holding the clock).
    Returns the (wall, sim) of every step."""
    steps = []
    while wall < until_wall:
        if hold is not None and hold[0] <= wall < hold[1]:
            wall = hold[1]
            continue
        ahead = pacer.ahead(sim_t, wall)
        if ahead <= 0:
            sim_t += DT
            steps.append((wall, sim_t))
        else:
            wall += min(ahead, DT) + 1e-9  # a wait of a float's rounding still passes time
    return steps


@pytest.mark.alone
def test_the_clock_keeps_the_rate_and_makes_up_a_short_hold_at_once() -> None:
    pacer = Pacer(1.0, catch_up_s=1.0)
    steps = run(pacer, 0.0, 100.0, 103.0, hold=(101.0, 101.3))
    sim_at = {round(w, 6): s for w, s in steps}
    assert max(s for w, s in steps if w < 101.0) == pytest.approx(1.0, abs=DT)  # real time before the hold
    # the 0.3 s held is made up the moment the hold ends: 30 steps at once, then the rate again
    assert sum(w == 101.3 for w, _ in steps) == pytest.approx(31, abs=1)
    assert sim_at[101.3] == pytest.approx(1.3 + DT, abs=DT / 2)  # the step due then taken too
    assert steps[-1][1] == pytest.approx(3.0, abs=DT)  # three wall seconds, three sim seconds


def test_a_hold_longer_than_the_catch_up_is_not_made_up() -> None:
    pacer = Pacer(2.0, catch_up_s=1.0)
    steps = run(pacer, 5.0, 0.0, 4.0, hold=(1.0, 2.5))
    assert max(s for w, s in steps if w < 1.0) == pytest.approx(7.0, abs=DT)  # twice real time
    assert sum(w == 2.5 for w, _ in steps) <= 1  # no burst of steps after 1.5 s held
    # from there on twice real time again: 1.5 s of wall time, 3 sim s
    assert steps[-1][1] - 7.0 == pytest.approx(3.0, abs=2 * DT)


def test_a_reset_or_a_restart_paces_from_there() -> None:
    pacer = Pacer(1.0)  # realtime: every lag is made up
    steps = run(pacer, 10.0, 0.0, 1.0)
    assert steps[-1][1] == pytest.approx(11.0, abs=DT)
    steps = run(pacer, 0.0, 1.0, 2.0)  # sim time went back (a reset through the API)
    assert steps[0][0] == 1.0 and steps[-1][1] == pytest.approx(1.0, abs=DT)
    pacer.restart(50.0, 10.0)  # the clock's owner (PX4) gave it back: no catching up the time it had it
    assert pacer.ahead(50.0, 10.0) == 0.0 and pacer.ahead(50.0 + DT, 10.0) == pytest.approx(DT)
    assert pacer.ahead(50.0 + DT, 12.0) == pytest.approx(DT - 2.0)  # unbounded catch-up, as --realtime has


def test_a_reset_to_the_time_the_run_started_at_paces_from_there() -> None:
    """A run from t = 0 reset to t = 0 (the API's reset): sim time went back, though not below where the
    pacing started. Found in a full run: the pacer saw no step back and ran the 3 s it believed it was
    behind unpaced, 3.6 s of sim time in 0.2 s of wall time, under a test streaming setpoints in real time."""
    pacer = Pacer(1.0)
    steps = run(pacer, 0.0, 0.0, 3.0)
    assert steps[-1][1] == pytest.approx(3.0, abs=DT)
    steps = run(pacer, 0.0, 3.0, 4.0)
    assert steps[-1][1] == pytest.approx(1.0, abs=DT) and len(steps) == pytest.approx(100, abs=1)


def test_bad_rates_are_refused() -> None:
    with pytest.raises(ValueError, match="rate must be positive"):
        Pacer(0.0)
    with pytest.raises(ValueError, match="catch_up_s must not be negative"):
        Pacer(1.0, catch_up_s=-1.0)
    assert Pacer(3.0).catch_up_s == math.inf
