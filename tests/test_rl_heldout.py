"""Held-out episodes of the vineyard task: the seed ranges of training, the stop check and evaluation never
meet, evaluation refuses seeds training or its stop check used, and every success rate carries its 95 %
Wilson score interval."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from droneulator.workflows.rl.heldout import (
    CHECK_EPISODES,
    CHECK_SEED,
    EVAL_EPISODES,
    EVAL_SEED,
    Z95,
    check_seeds,
    interval_record,
    rate_text,
    wilson_interval,
)


# --------------------------------------------------------------------------- the Wilson score interval
def wilson_by_roots(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The interval's definition, solved independently: the p with (k/n - p)^2 = z^2 p (1 - p) / n, the
    roots of (1 + z^2/n) p^2 - (2 k/n + z^2/n) p + (k/n)^2 = 0."""
    ph, c = k / n, z * z / n
    roots = np.sort(np.roots([1 + c, -(2 * ph + c), ph * ph]).real)
    return float(roots[0]), float(roots[1])


def test_wilson_interval_matches_published_values_and_the_definition():
    # 45/50 (the issue's): [0.786, 0.957]; 9/10: [0.596, 0.982]; 34/50 (the 68 %): [0.542, 0.792]
    for (k, n), (low, high) in {
        (45, 50): (0.786, 0.957),
        (9, 10): (0.596, 0.982),
        (34, 50): (0.542, 0.792),
        (5, 10): (0.237, 0.763),  # symmetric about 0.5
    }.items():
        got = wilson_interval(k, n)
        assert got == pytest.approx((low, high), abs=6e-4), (k, n, got)
        assert got == pytest.approx(wilson_by_roots(k, n, Z95), abs=1e-9), (k, n)
    for k, n in ((1, 7), (3, 20), (17, 20), (49, 50), (123, 400)):
        assert wilson_interval(k, n) == pytest.approx(wilson_by_roots(k, n, Z95), abs=1e-9), (k, n)
    assert abs(Z95 - 1.959964) < 1e-6


def test_wilson_interval_at_none_and_all_and_bad_counts():
    z2 = Z95**2
    for n in (1, 10, 50):
        low, high = wilson_interval(0, n)
        assert low == 0.0 and high == pytest.approx(z2 / (n + z2), abs=1e-12)  # 0/10: 0.2775
        low, high = wilson_interval(n, n)
        assert high == 1.0 and low == pytest.approx(n / (n + z2), abs=1e-12)  # 10/10: 0.7225
    assert wilson_interval(0, 10)[1] == pytest.approx(0.2775, abs=1e-4)
    assert wilson_interval(10, 10)[0] == pytest.approx(0.7225, abs=1e-4)
    for k, n in ((0, 0), (-1, 10), (11, 10)):
        with pytest.raises(ValueError, match="success"):
            wilson_interval(k, n)


def test_a_rate_as_printed_and_recorded():
    assert rate_text(45, 50) == "45/50 (90 %, 95 % CI 79-96 %)"
    assert rate_text(0, 50) == "0/50 (0 %, 95 % CI 0-7 %)"
    rec = interval_record(50, 50)
    assert rec["successes"] == 50 and rec["episodes"] == 50 and rec["success_rate"] == 1.0
    assert rec["success_interval_95"][1] == 1.0 and rec["success_interval_95"][0] == pytest.approx(0.9287)
    json.dumps(rec)  # it goes into the summaries


# --------------------------------------------------------------------------- seed ranges
def test_the_check_seeds_meet_no_training_or_evaluation_seed():
    assert CHECK_EPISODES == 50 and EVAL_EPISODES == 50
    checks = set(check_seeds())
    assert checks == set(range(CHECK_SEED, CHECK_SEED + 50)) and check_seeds(3) == [
        CHECK_SEED + i for i in range(3)
    ]
    evaluation = set(range(EVAL_SEED, EVAL_SEED + EVAL_EPISODES))
    further = set(range(EVAL_SEED + 100, EVAL_SEED + 150))  # benchmarks/rl.py and realism.py's 50
    assert not checks & evaluation and not checks & further
    assert abs(CHECK_SEED - EVAL_SEED) >= 1_000_000  # far apart: a bigger --episodes stays clear
    # training: seed + i for the worlds of a run (up to 4096 of them, seeds up to 100,000), and the seeds a
    # restarted Ray actor's worlds take (seed + RESTART_SEED_STRIDE * restarts + i)
    stride = 1_000_003  # ray_vec.RESTART_SEED_STRIDE (not imported here: it needs Ray's SB3 wrapper)
    for restarts in range(3):
        low = restarts * stride
        assert not set(range(low, low + 100_000 + 4096)) & (
            checks | set(range(CHECK_SEED, CHECK_SEED + 10_000))
        )
    assert not set(range(0, 100_000 + 4096)) & evaluation
    with pytest.raises(ValueError, match="--check-episodes must be at least 1"):
        check_seeds(0)


def test_ray_restart_stride_is_the_one_the_seed_test_assumes():
    text = (Path(__file__).parents[1] / "droneulator" / "workflows" / "rl" / "ray_vec.py").read_text()
    assert "RESTART_SEED_STRIDE = 1_000_003" in text


# --------------------------------------------------------------------------- evaluate refuses used seeds
def _run(tmp_path: Path, **summary: object) -> Path:
    run = tmp_path / "run"
    run.mkdir()
    (run / "model.zip").write_bytes(b"not read: the seeds are refused first")
    (run / "train_summary.json").write_text(json.dumps({"algo": "sac", **summary}))
    return run


def test_evaluate_refuses_seeds_its_stop_check_or_training_flew(tmp_path, capsys):
    pytest.importorskip("stable_baselines3")
    from droneulator.cli import main
    from droneulator.workflows.rl.evaluate import evaluate, stop_check_seeds, training_seeds

    run = _run(tmp_path, train_seeds=[3, 4], stop_at=0.9, check_seeds=check_seeds(50))
    assert training_seeds(run / "model.zip") == [3, 4]
    assert stop_check_seeds(run / "model.zip") == check_seeds(50)
    with pytest.raises(ValueError, match=r"used by its stop check: pick another --seed"):
        evaluate(run, seed=CHECK_SEED + 40)
    with pytest.raises(ValueError, match=r"\[4\] were used in training"):
        evaluate(run, episodes=2, seed=4)
    with pytest.raises(ValueError, match="--episodes must be at least 1"):
        evaluate(run, episodes=0)
    for args, message in (
        (
            ["--seed", str(CHECK_SEED - 10)],
            f"evaluation seeds {CHECK_SEED}..{CHECK_SEED + 39} (40) were used by",
        ),
        (["--episodes", "0"], "--episodes must be at least 1"),
    ):
        assert main(["evaluate", str(run), *args]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err


def test_an_older_summary_without_check_seeds_keeps_working(tmp_path):
    from droneulator.workflows.rl.evaluate import _legacy_warning, stop_check_seeds, training_seeds

    run = _run(tmp_path, train_seeds=[0], stop_at=0.9, checks=[{"steps": 10_000, "successes": 9}])
    model = run / "model.zip"
    assert stop_check_seeds(model) == [] and training_seeds(model) == [0]
    # it was stopped on seeds 1,000,000 to 1,000,009: an evaluation there is not refused, but noted
    assert "1000000 to 1000009" in _legacy_warning(model, list(range(EVAL_SEED, EVAL_SEED + 50)))
    assert _legacy_warning(model, list(range(EVAL_SEED + 10, EVAL_SEED + 60))) is None
    (run / "train_summary.json").write_text(json.dumps({"train_seeds": [0]}))  # no stop check at all
    assert _legacy_warning(model, [EVAL_SEED]) is None and stop_check_seeds(tmp_path / "none" / "m.zip") == []


# --------------------------------------------------------------------------- the command line
def test_check_episodes_below_one_is_a_one_line_error(capsys):
    from droneulator.cli import main

    for args in (
        ["train", "--stop-at", "0.9", "--check-episodes", "0"],
        ["train", "--num-envs", "4", "--stop-at", "0.9", "--check-episodes", "-3"],
        ["train", "--ray", "local", "--check-episodes", "0"],
    ):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert "--check-episodes must be at least 1" in err and err.count("\n") == 1, (args, err)
    assert (
        main(["train", "--num-envs", "4", "--check-episodes", "20"]) == 2
    )  # nothing to check without --stop-at
    err = capsys.readouterr().err
    assert "--check-episodes goes with --stop-at" in err and err.count("\n") == 1, err


def test_training_seeds_on_the_check_seeds_are_refused(tmp_path, capsys):
    pytest.importorskip("stable_baselines3")
    from droneulator.cli import main

    args = [
        "train",
        "--num-envs",
        "4",
        "--stop-at",
        "0.9",
        "--seed",
        str(CHECK_SEED - 2),
        "--out",
        str(tmp_path),
    ]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert (
        f"training seeds {CHECK_SEED}..{CHECK_SEED + 1} are stop-check seeds" in err and err.count("\n") == 1
    )


def test_help_gives_the_new_defaults_and_warns_of_a_small_gate():
    from droneulator.cli import build_parser

    ap = build_parser()
    sub = next(a for a in ap._actions if a.__class__.__name__ == "_SubParsersAction")
    train = " ".join(sub.choices["train"].format_help().split())
    evaluate = " ".join(sub.choices["evaluate"].format_help().split())
    assert (
        "--check-episodes N" in train and "(default 50" in train and "Fewer than 50 is a weak gate" in train
    )
    assert f"seeds from {CHECK_SEED}" in train and "10 held-out" not in train
    assert "episodes (default 50" in evaluate and "95 % Wilson interval" in evaluate
    assert sub.choices["evaluate"].parse_args(["m"]).episodes == 50


def test_the_stop_check_flies_all_its_episodes_on_one_batched_env():
    pytest.importorskip("stable_baselines3")
    from droneulator.workflows.rl.env import env_config
    from droneulator.workflows.rl.train import _success_check, passes

    check = _success_check(env_config(None), 10_000, 0.9, "raycast", None, check_seeds())
    try:
        assert check.env.num_envs == 50 and check.seeds == check_seeds()
    finally:
        check.env.close()
    assert passes(45, 50, 0.9) and not passes(44, 50, 0.9) and passes(9, 10, 0.9) and passes(50, 50, 1.0)
    assert not passes(49, 50, 1.0) and passes(35, 50, 0.7) and math.isclose(0.9 * 50, 45.0)


def test_rllib_training_seeds_on_the_check_seeds_are_refused_before_ray_starts(tmp_path, capsys):
    pytest.importorskip("ray")
    from droneulator.cli import main

    # RLlib seeds env runner k's worlds seed + k + i: 2 runners of 8 worlds, seed to seed + 9
    args = ["train", "--ray", "local", "--env-runners", "2", "--num-envs", "8", "--out", str(tmp_path)]
    assert main([*args, "--seed", str(CHECK_SEED - 8)]) == 2
    err = capsys.readouterr().err
    assert f"training seeds {CHECK_SEED}..{CHECK_SEED + 1} are stop-check seeds" in err, err
    assert err.count("\n") == 1 and not (tmp_path / "config.json").exists()
