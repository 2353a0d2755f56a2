"""The Gymnasium environment ``droneulator/VineyardNav-v0``: a few steps of a scripted policy.

``import droneulator`` registers the environment (docs/rl.md). The observation is a 35-vector: a
32-sample depth strip (normalised, 1.0 = nothing within 10 m), the heading error to the goal's
A* path divided by pi, the forward speed and the yaw rate; the action is two numbers in [-1, 1]
(forward speed and yaw rate, through velocity mode). One step is one camera frame of sim time.

    python examples/gym_vineyard.py --episodes 2 --steps 150

The policy here is a hand-written one, not a trained one: turn toward the path (observation [32])
and slow down when the centre of the depth strip is close. ``droneulator train`` learns a better one
(SAC, needs the pip install of the ``rl`` extra); this script needs only the core package.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np

import droneulator  # noqa: F401 (registers droneulator/VineyardNav-v0)
from droneulator.workflows.rl import ENV_ID


def scripted_action(obs: np.ndarray) -> np.ndarray:
    """Steer toward the path and slow down near obstacles ahead: forward in [-1, 1], yaw rate in [-1, 1]."""
    strip, heading = obs[:32], float(obs[32])
    ahead = float(strip[12:20].min())  # nearest return in the central quarter of the view, 0..1
    forward = -0.2 + 0.8 * np.clip((ahead - 0.15) / 0.35, 0.0, 1.0)  # -0.2: ~0 m/s, 0.6: ~2 m/s
    yaw_rate = np.clip(3.0 * heading, -1.0, 1.0)
    return np.array([forward, yaw_rate], dtype=np.float32)


def run(episodes: int, steps: int, seed: int, random_actions: bool) -> list[dict]:
    """Roll out ``episodes`` episodes of at most ``steps`` steps; one summary per episode."""
    env = gym.make(ENV_ID)
    env.action_space.seed(seed)
    results = []
    try:
        for ep in range(episodes):
            obs, info = env.reset(seed=seed + ep)
            assert env.observation_space.contains(obs), "observation outside the declared space"
            total, n, end = 0.0, 0, "step_limit"
            start_distance = info["distance"]
            for n in range(1, steps + 1):  # noqa: B007 (n is reported after the loop)
                action = env.action_space.sample() if random_actions else scripted_action(obs)
                obs, reward, terminated, truncated, info = env.step(action)
                total += reward
                if terminated or truncated:
                    end = info["termination"]
                    break
            results.append(
                {
                    "episode": ep,
                    "seed": seed + ep,
                    "steps": n,
                    "sim_time_s": info["t"],
                    "return": total,
                    "start_path_distance_m": start_distance,
                    "path_distance_m": info["distance"],
                    "end": end,
                    "observation_shape": list(obs.shape),
                }
            )
            print(
                f"episode {ep} (seed {seed + ep}): {n} steps, {info['t']:.1f} s sim, return {total:7.2f}, "
                f"path to goal {start_distance:.1f} -> {info['distance']:.1f} m, end: {end}"
            )
    finally:
        env.close()
    return results


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=2, help="episodes to run")
    ap.add_argument("--steps", type=int, default=150, help="maximum steps per episode (30 per sim second)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the first episode's start and goal")
    ap.add_argument("--random", action="store_true", help="random actions instead of the scripted policy")
    ap.add_argument("--summary", default=None, help="write the per-episode results as JSON")
    args = ap.parse_args()
    if args.episodes < 1 or args.steps < 1:
        ap.error("--episodes and --steps must be at least 1")
    results = run(args.episodes, args.steps, args.seed, args.random)
    if args.summary:
        Path(args.summary).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
