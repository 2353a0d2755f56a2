"""Held-out episodes of the vineyard task: whose seeds they fly, how many, and how sure a success rate is.

Three seed ranges never meet:

* training: ``seed`` to ``seed + envs - 1`` (``droneulator train --seed``; later training episodes draw
  from those seeds' generators);
* the stop check during training (``train --stop-at``) and the RLlib run's final check:
  :data:`CHECK_EPISODES` episodes from :data:`CHECK_SEED` (:func:`check_seeds`);
* evaluation (``droneulator evaluate``): :data:`EVAL_EPISODES` episodes from :data:`EVAL_SEED`, so a
  figure reported after training was not used to decide when to stop.

Every success rate reported comes with its 95 % Wilson score interval (:func:`wilson_interval`). On 10
episodes a policy that succeeds 70 % of the time passes a 9/10 gate about one time in seven, and 9/10
says only that the rate is somewhere in [0.60, 0.98]; on 50 episodes 45/50 says [0.79, 0.96].

Numbers only, no imports beyond the standard library: the CLI's help and the tests read it cheaply.
"""

from __future__ import annotations

import math

#: the first evaluation seed (``droneulator evaluate --seed``): far from every training seed
EVAL_SEED = 1_000_000
#: evaluation episodes by default (``droneulator evaluate --episodes``)
EVAL_EPISODES = 50
#: the first seed of the stop check (``train --stop-at``) and of the RLlib run's final check: far from
#: the evaluation seeds, and between the seeds a restarted Ray actor's worlds take
#: (``seed + 1,000,003 x restarts + i``, :data:`~droneulator.workflows.rl.ray_vec.RESTART_SEED_STRIDE`)
CHECK_SEED = 2_500_000
#: held-out episodes each stop check flies by default (``train --check-episodes``), batched on one vector
#: env. Fewer than 50 is a weak gate: at 10, a 70 % policy reaches 9/10 about one time in seven
CHECK_EPISODES = 50
#: the normal quantile of a two-sided 95 % interval
Z95 = 1.959963984540054


def check_seeds(episodes: int = CHECK_EPISODES) -> list[int]:
    """The seeds the stop check flies: ``episodes`` of them from :data:`CHECK_SEED`."""
    if episodes < 1:
        raise ValueError(f"--check-episodes must be at least 1, got {episodes}")
    return list(range(CHECK_SEED, CHECK_SEED + episodes))


def refuse_overlap(training: range | list[int], checks: list[int]) -> None:
    """A one-line error when training seeds meet the stop check's (``checks``)."""
    clash = sorted(set(training) & set(checks))
    if clash:
        raise ValueError(
            f"training seeds {clash[0]}..{clash[-1]} are stop-check seeds ({checks[0]}..{checks[-1]}): "
            "pick another --seed"
        )


def wilson_interval(successes: int, episodes: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval of a success rate, ``successes`` of ``episodes`` (95 % by default):
    ``(p + z²/2n ± z sqrt(p(1-p)/n + z²/4n²)) / (1 + z²/n)``; 0 and 1 exactly at 0/n and n/n."""
    if episodes < 1 or not 0 <= successes <= episodes:
        raise ValueError(f"a success rate needs 0 <= successes <= episodes >= 1, got {successes}/{episodes}")
    n, p = episodes, successes / episodes
    scale = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / scale
    half = z * math.sqrt(p * (1.0 - p) / n + z * z / (4 * n * n)) / scale
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == episodes else min(1.0, centre + half)
    return low, high


def rate_text(successes: int, episodes: int) -> str:
    """``45/50 (90 %, 95 % CI 79-96 %)``: a success rate as every command prints it."""
    low, high = wilson_interval(successes, episodes)
    return (
        f"{successes}/{episodes} ({100 * successes / episodes:.0f} %, "
        f"95 % CI {100 * low:.0f}-{100 * high:.0f} %)"
    )


def interval_record(successes: int, episodes: int) -> dict[str, object]:
    """The JSON fields of a success rate: count, episodes, rate and its 95 % Wilson interval."""
    low, high = wilson_interval(successes, episodes)
    return {
        "successes": successes,
        "episodes": episodes,
        "success_rate": successes / episodes,
        "success_interval_95": [round(low, 4), round(high, 4)],
    }
