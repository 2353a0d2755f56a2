"""Pacing the simulation clock by the wall clock: ``--realtime``'s speed and lockstep's ``runtime.max_speed``.

A :class:`Pacer` keeps sim time at ``rate`` simulated seconds per wall second from an anchor. When the
steps fall behind (a slow step; in lockstep, a frame that holds the clock while it is rendered and
published) the steps run unpaced until sim time has made the wait up, so that the rate holds on average
and a run capped at real time keeps real time; a wait longer than ``catch_up_s`` is not made up (a
consumer that cannot keep up, a client that paused the run): pacing starts again from there, with no
burst of steps.
"""

from __future__ import annotations

import math


class Pacer:
    """When the next step of the simulation clock is due, at ``rate`` sim s per wall s."""

    def __init__(self, rate: float, catch_up_s: float = math.inf) -> None:
        if not rate > 0:
            raise ValueError(f"the pacing rate must be positive, got {rate}")
        if not catch_up_s >= 0:
            raise ValueError(f"catch_up_s must not be negative, got {catch_up_s}")
        self.rate = rate
        self.catch_up_s = catch_up_s
        self.wall0: float | None = None
        self.sim0 = 0.0
        self._last = -math.inf  # the latest sim time asked about: a reset is a step back from it

    def restart(self, sim_t: float, now: float) -> None:
        """Pace from here: sim time ``sim_t`` at wall time ``now`` (a reset, or the clock's owner changed)."""
        self.wall0, self.sim0, self._last = now, sim_t, sim_t

    def ahead(self, sim_t: float, now: float) -> float:
        """How far (wall s) sim time ``sim_t`` is ahead of the pace at wall time ``now``: the time to wait
        before the next step, when positive. Restarts the pacing first when sim time went back (a reset)
        or fell further behind than ``catch_up_s``."""
        if self.wall0 is None or sim_t < self._last:
            self.restart(sim_t, now)
        self._last = sim_t
        ahead = (sim_t - self.sim0) / self.rate - (now - self.wall0)
        if ahead < -self.catch_up_s:
            self.restart(sim_t, now)
            return 0.0
        return ahead
