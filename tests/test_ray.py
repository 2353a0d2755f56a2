"""Past one machine on Ray: training on RLlib and dataset sweeps on a real two-node Ray cluster (two
raylets on this machine, ``ray.cluster_utils.Cluster``), with the failures a cluster has: an env runner
killed mid-training, a sweep interrupted and run again."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import ray
from ray.cluster_utils import Cluster

from droneulator.cli import main
from droneulator.config import load_config
from droneulator.runtime.cluster import ClusterError, check_address, connect
from droneulator.workflows.rl.env import env_config
from droneulator.workflows.rl.ray_vec import RayVecEnv
from droneulator.workflows.rl.rllib import algorithm_config, train_on_ray
from droneulator.workflows.rl.train import PPO_HYPERPARAMETERS, SAC_HYPERPARAMETERS, make_vec_env
from droneulator.workflows.sweep import Job, make_jobs, parse_seeds

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


@pytest.fixture(scope="module")
def cluster() -> Any:
    """A head node and a worker node, one CPU each: Ray places work on both."""
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    c.add_node(num_cpus=1)
    c.wait_for_nodes()
    yield c
    c.shutdown()


@pytest.mark.slow
def test_training_on_two_nodes_survives_a_killed_env_runner_and_resumes(cluster: Any, tmp_path: Path) -> None:
    """PPO on RLlib, two env runners of 16 batched worlds: they run on both nodes; one is SIGKILLed after
    the second iteration, RLlib restarts it and training reaches its steps with both runners healthy;
    checkpoint, progress and TensorBoard logs are written, and a resumed run goes on from the checkpoint."""
    out = tmp_path / "run"
    seen: list[dict[str, Any]] = []
    threads: list[tuple[int, int]] = []

    def _threads(_runner: Any) -> tuple[int, int]:
        """(numba threads, torch threads) of an env runner's process (nested: pickled by value)."""
        import numba
        import torch

        return numba.get_num_threads(), torch.get_num_threads()

    def on_iteration(algorithm: Any, result: dict[str, Any]) -> None:
        where = algorithm.env_runner_group.foreach_env_runner(
            lambda _runner: (os.getpid(), ray.get_runtime_context().get_node_id()), local_env_runner=False
        )
        seen.append({"iteration": result["training_iteration"], "runners": where})
        threads.extend(algorithm.env_runner_group.foreach_env_runner(_threads, local_env_runner=False))
        if result["training_iteration"] == 2:
            os.kill(where[0][0], signal.SIGKILL)
        group = algorithm.env_runner_group
        if result["training_iteration"] == 4 and group.num_remote_worker_restarts() == 0:
            # Ray restarts the actor in the background, which on a loaded machine (a fresh worker
            # importing torch) outlasts the last iterations: bring it back as the next train() would
            deadline = time.monotonic() + 180
            while not algorithm.restore_env_runners(group) and time.monotonic() < deadline:
                time.sleep(0.5)

    steps = 2 * 16 * 32 * 6  # six iterations' worth
    summary = train_on_ray(
        None,
        out,
        address=cluster.address,
        steps=steps,
        env_runners=2,
        num_envs=16,
        restart_delay_s=1.0,
        progress=False,
        on_iteration=on_iteration,
        check_episodes=10,  # 50 by default
    )
    assert len({node for _pid, node in seen[0]["runners"]}) == 2  # one env runner on each node
    # each runner, restarted ones too, on its one CPU: one numba and one torch thread (not every core's)
    assert len(threads) == sum(len(s["runners"]) for s in seen) and set(threads) == {(1, 1)}
    assert summary["ray_nodes"] == 2 and summary["steps"] >= steps
    assert summary["env_runner_restarts"] == 1 and summary["healthy_env_runners"] == 2
    killed = seen[1]["runners"][0][0]
    assert killed not in dict(seen[-1]["runners"]) and len(seen[-1]["runners"]) == 2  # a new process
    rows = list(csv.DictReader((out / "progress.csv").open()))
    assert len(rows) == len(seen) and int(rows[-1]["env_steps"]) == summary["steps"]
    healthy = [int(r["healthy_env_runners"]) for r in rows]
    assert healthy[:2] == [2, 2] and 1 in healthy[2:] and healthy[-1] == 2  # trained on with one meanwhile
    assert (out / "checkpoint" / "algorithm_state.pkl").is_file()
    assert list((out / "tb").glob("events.out.tfevents.*"))
    assert 0 <= summary["held_out_successes"] <= 10 and summary["held_out_episodes"] == 10
    assert summary["check_seeds"] == list(range(2_500_000, 2_500_010))
    low, high = summary["held_out_interval_95"]
    assert 0.0 <= low <= summary["held_out_successes"] / 10 <= high <= 1.0

    resumed = train_on_ray(
        None, out, address=cluster.address, steps=summary["steps"] + 1, env_runners=2, num_envs=16,
        resume=True, progress=False, check_episodes=10,
    )  # fmt: skip
    rows = list(csv.DictReader((out / "progress.csv").open()))
    assert resumed["resumed"] and resumed["steps"] > summary["steps"]
    assert int(rows[len(seen)]["env_steps"]) > summary["steps"]  # counted on from the checkpoint, not from 0
    assert resumed["wall_s"] > summary["wall_s"]


@pytest.mark.slow
def test_a_sweep_interrupted_and_run_again_does_not_redo_finished_jobs(cluster: Any, tmp_path: Path) -> None:
    """``sweep capture`` of 4 small captures as Ray tasks on the two nodes (two at a time), Ctrl-C once the
    first two are done and the others have started; the same command again runs only those two; every
    dataset holds its views and the summary lists all four."""
    out = tmp_path / "sweep"
    cmd = [
        sys.executable, "-m", "droneulator.cli", "sweep", "capture", "--out", str(out), "--seeds", "0-1",
        "--views", "2", "3", "--ray", cluster.address, "--cpus-per-job", "1", "--no-progress",
        "--set", "capture.width=160", "--set", "capture.height=120", "--set", "capture.arc_deg=20",
        "--set", "capture.speed=2", "--set", "capture.pitch_deg=10", "--set", "render.shadow_map_size=512",
        "--set", "randomize.enabled=true", "--set", "randomize.wind_speed_m_s=[0, 2]",
        "--set", "capture.accept_after_s=0.5",
    ]  # fmt: skip
    first = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV)
    deadline = time.monotonic() + 240
    while len(list(out.glob("*/job.json"))) < 2:
        assert first.poll() is None and time.monotonic() < deadline, first.communicate()[0]
        time.sleep(0.2)
    first.send_signal(signal.SIGINT)
    log = first.communicate(timeout=60)[0]
    assert first.returncode == 130, log
    assert "run the same command again to resume" in log
    done = {p.parent.name: p.stat().st_mtime_ns for p in out.glob("*/job.json")}
    assert 2 <= len(done) < 4

    again = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=300)
    assert again.returncode == 0, again.stdout + again.stderr
    assert f"{len(done)} already done" in again.stderr and f"{4 - len(done)} to run" in again.stderr
    after = {p.parent.name: p.stat().st_mtime_ns for p in out.glob("*/job.json")}
    assert len(after) == 4 and all(after[name] == t for name, t in done.items())  # not redone
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert sorted(r["name"] for r in rows) == sorted(j.name for j in make_jobs("capture", ["tree_inspection"],
                                                                               [0, 1], [2, 3]))  # fmt: skip
    conditions = []
    for row in rows:
        folder = out / row["name"]
        views = int(row["name"].rsplit("views", 1)[1])
        assert row["status"] == "done" and int(row["views_captured"]) == views
        assert len(list((folder / "images").glob("*.jpg"))) == views
        assert json.loads((folder / "config.json").read_text())["capture"]["views"] == views
        meta = json.loads((folder / "metadata.json").read_text())
        assert meta["complete"]
        conditions.append(meta["plan"]["conditions"])  # domain randomisation: each job its own draw
    assert len({json.dumps(c, sort_keys=True) for c in conditions}) == 2  # one draw per seed
    assert "tree_inspection-seed1-views3" in again.stdout  # the table


@pytest.mark.slow
def test_sb3_worlds_in_ray_actors_equal_the_in_process_env_and_survive_a_killed_actor(
    cluster: Any, tmp_path: Path
) -> None:
    """``--ray-backend sb3``: 16 worlds in two Ray actors (one on each node) step exactly as the 16 worlds
    of the in-process env with the same seed and actions, autoresets included; a SIGKILLed actor is started
    again, its worlds' episodes end truncated at their last observation and new ones begin, the others
    go on untouched; and a short PPO run through the command writes its model, logs and summary."""
    cfg = env_config(load_config())
    with connect(cluster.address):
        remote = RayVecEnv(cfg, 16, 2)
        local = make_vec_env(cfg, 16, "native").venv
        try:
            assert len({node for _, node in remote.where()}) == 2
            remote.seed(3)
            local.seed(3)
            np.testing.assert_array_equal(remote.reset(), local.reset())
            rng = np.random.default_rng(0)
            ended = 0
            for _ in range(250):
                actions = rng.uniform(-1, 1, (16, 2)).astype(np.float32)
                remote.step_async(actions)
                local.step_async(actions)
                got, want = remote.step_wait(), local.step_wait()
                for a, b in zip(got[:3], want[:3], strict=True):
                    np.testing.assert_array_equal(a, b)
                for a, b in zip(got[3], want[3], strict=True):
                    assert a.keys() == b.keys() and a["termination"] == b["termination"]
                    if "terminal_observation" in b:
                        np.testing.assert_array_equal(a["terminal_observation"], b["terminal_observation"])
                ended += int(want[2].sum())
            assert ended > 0  # autoresets happened on the way
            before = got[0]
            pid = remote.where()[1][0]
            os.kill(pid, signal.SIGKILL)
            actions = rng.uniform(-1, 1, (16, 2)).astype(np.float32)
            remote.step_async(actions)
            local.step_async(actions)
            obs, rewards, dones, infos = remote.step_wait()
            want = local.step_wait()
            assert remote.restarts == 1 and remote.where()[1][0] != pid
            restarted = list(range(3 + 1_000_003 + 8, 3 + 1_000_003 + 16))  # RESTART_SEED_STRIDE, worlds 8-15
            assert remote.seeds_used == list(range(3, 19)) + restarted  # train_summary's train_seeds
            assert dones[8:].all() and (rewards[8:] == 0).all()
            for i in range(8, 16):
                assert infos[i]["TimeLimit.truncated"] and infos[i]["termination"] == "env_restarted"
                np.testing.assert_array_equal(infos[i]["terminal_observation"], before[i])
            np.testing.assert_array_equal(obs[:8], want[0][:8])  # the other actor's worlds go on
            assert not np.array_equal(obs[8:], before[8:])  # new episodes
        finally:
            remote.close()
            local.close()

    out = tmp_path / "sb3"
    code = main([
        "train", "--ray", cluster.address, "--ray-backend", "sb3", "--env-runners", "2", "--num-envs", "16",
        "--algo", "ppo", "--steps", "1024", "--out", str(out), "--no-progress",
    ])  # fmt: skip
    assert code == 0
    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["vec"] == "ray" and summary["ray_actors"] == 2 and summary["ray_nodes"] == 2
    assert summary["steps"] >= 1024 and summary["actor_restarts"] == 0
    assert (out / "model.zip").is_file() and list((out / "tb").rglob("events.out.tfevents.*"))
    assert not ray.is_initialized()


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_both_algorithms_pass_rllibs_own_validation_with_the_sb3_runs_settings(algo: str) -> None:
    """RLlib validates each config as it builds it (SAC's rollouts must hold its n-step return); the
    settings are the SB3 runs', read from one table."""
    config = algorithm_config(load_config(), algo, env_runners=2, num_envs=16, seed=0)
    config.validate()
    hyper = PPO_HYPERPARAMETERS if algo == "ppo" else SAC_HYPERPARAMETERS
    assert config.rollout_fragment_length == hyper["n_steps"] and config.gamma == hyper["gamma"]
    assert config.num_envs_per_env_runner == 16 and config.gym_env_vectorize_mode == "vector_entry_point"
    if algo == "ppo":
        assert config.train_batch_size_per_learner == 2 * 16 * hyper["n_steps"]
        assert config.minibatch_size == min(hyper["batch_size"], 2 * 16 * hyper["n_steps"])
    else:
        assert config.n_step == hyper["n_steps"] and config.actor_lr == hyper["learning_rate"]
        assert config.replay_buffer_config["capacity"] == hyper["buffer_size"]


def test_seeds_jobs_and_addresses_are_checked() -> None:
    assert parse_seeds(["0-3", "7", "2"]) == [0, 1, 2, 3, 7]
    for bad in (["3-1"], ["x"], ["-2"], []):
        with pytest.raises(ValueError):
            parse_seeds(bad)
    jobs = make_jobs("capture", ["tree_inspection", "orchard"], [0, 1], [18, 36])
    assert len(jobs) == 8 and jobs[0] == Job("capture", "tree_inspection", 0, 18)
    assert jobs[-1].name == "orchard-seed1-views36"
    assert make_jobs("plan", ["planning"], [4])[0].name == "planning-seed4"
    with pytest.raises(ValueError, match="unknown scene"):
        make_jobs("capture", ["nowhere"], [0], [18])
    with pytest.raises(ValueError, match="capture setting"):
        make_jobs("plan", ["planning"], [0], [18])
    assert check_address("local") == "local" and check_address("ray://10.0.0.1:10001")
    for bad in ("", "10.0.0.1", "head:port", "head:0"):
        with pytest.raises(ValueError, match="HOST:PORT"):
            check_address(bad)
    t = time.monotonic()
    with pytest.raises(ClusterError, match="no Ray head node answers"), connect("127.0.0.1:9"):
        pass
    assert time.monotonic() - t < 10  # Ray itself would retry for minutes


def test_bad_ray_settings_are_one_line_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Each is refused before Ray starts, in the command's own process (``cli.main``), with one line."""
    (tmp_path / "run" / "checkpoint").mkdir(parents=True)
    cases = [
        (["train", "--ray", "local", "--stop-at", "0.9"], "--stop-at: not with --ray"),
        (["train", "--env-runners", "2"], "go with --ray"),
        (["train", "--ray", "nowhere"], "HOST:PORT"),
        (["train", "--ray", "local", "--resume", "--out", str(tmp_path / "none")], "no checkpoint"),
        (["train", "--ray", "local", "--out", str(tmp_path / "run")], "holds a run already"),
        (
            ["train", "--ray", "local", "--ray-backend", "sb3", "--resume"],
            "--resume: not with --ray-backend sb3",
        ),
        (
            ["train", "--ray", "local", "--ray-backend", "sb3", "--num-envs", "4", "--env-runners", "5"],
            "--env-runners must be between 1 and --num-envs (4)",
        ),
        (["sweep", "plan", "--out", str(tmp_path / "s"), "--reconstruct"], "goes with sweep capture"),
        (["sweep", "capture", "--out", str(tmp_path / "s"), "--seeds", "9-2"], "ends before it starts"),
        (["sweep", "plan", "--out", str(tmp_path / "s"), "--set", "seed=1"], "no --config or --set"),
    ]
    for args, message in cases:
        code = main(args)
        err = capsys.readouterr().err
        assert code == 2, (args, err)
        assert message in err and err.count("\n") == 1, (args, err)
    assert not ray.is_initialized()
