"""Experiments, episodes, recordings and the leaderboard from Python
(issue 23, item 5): an embedded env asked about its own experiment, and a
controller in another process asked by three users with their own tokens."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import gymnasium
import pytest

import offworld_gym
from conftest import _binary, start_controller, stop
from offworld_gym import errors


def _play(env: gymnasium.Env, seed: int, max_steps: int) -> tuple[int, float, bool]:
    """One episode from ``seed``: (steps, return, ended by itself)."""
    env.reset(seed=seed)
    steps, total = 0, 0.0
    for _ in range(max_steps):
        _, reward, terminated, truncated, _ = env.step(2)
        steps += 1
        total += float(reward)
        if terminated or truncated:
            return steps, total, True
    return steps, total, False


def test_an_embedded_env_lists_its_episodes_with_their_recordings(tmp_path: Path) -> None:
    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", resolution=(12, 16), record=tmp_path)
    try:
        played = [_play(env, seed, 4) for seed in (21, 22)]
        env.reset(seed=23)  # ends episode 1; episode 2 is in progress
        experiment = env.unwrapped.experiment()
        episodes = env.unwrapped.episodes()
    finally:
        env.close()
    assert experiment["id"] == env.unwrapped.experiment_id
    assert experiment["name"] == env.unwrapped.experiment_name
    assert (experiment["user"], experiment["task"], experiment["learning_type"], experiment["algorithm_mode"]) == (
        "anonymous",
        "MonolithDiscrete",
        "end2end",
        "train",
    )
    assert experiment["episodes"] == 3
    assert [e["index"] for e in episodes] == [0, 1, 2]
    assert [e["seed"] for e in episodes] == [21, 22, 23]
    for episode, (steps, total, ended) in zip(episodes, played):
        assert (episode["steps"], episode["episode_return"]) == (steps, total)
        assert (episode["end_reason"] == "reset before the episode ended") == (not ended)
        assert episode["started_unix_ms"] <= episode["ended_unix_ms"]
    assert episodes[2]["end_reason"] == "in_progress"
    # Each keeps how well its reset put the robot at its spawn pose.
    for episode in episodes:
        reset = episode["reset"]
        assert reset is not None
        assert set(reset) == {"requested", "achieved", "position_error_m", "yaw_error_rad", "duration_s", "unix_ms"}
        (rx, ry, _), (ax, ay, _) = reset["requested"], reset["achieved"]
        assert abs(((ax - rx) ** 2 + (ay - ry) ** 2) ** 0.5 - reset["position_error_m"]) < 1e-9
        # A twin teleports there: within a millimetre.
        assert reset["position_error_m"] < 0.001 and reset["yaw_error_rad"] < 0.001
        assert reset["duration_s"] > 0.0
        assert reset["unix_ms"] == episode["started_unix_ms"]
    # Each episode names its MCAP file under the record directory.
    for episode in episodes:
        (recording,) = episode["recordings"]
        assert recording["path"] == (
            f"sim/{experiment['env_id'].split('/')[1]}/exp-{experiment['id']:06}/ep-{episode['index']:06}.mcap"
            + ("" if recording["complete"] else ".partial")
        )
        assert recording["complete"] == (episode["index"] < 2)
        if recording["complete"]:
            assert (tmp_path / recording["path"]).stat().st_size == recording["bytes"]


def _add_user(db: Path, name: str, *operator: str) -> str:
    made = subprocess.run(
        [str(_binary("env_controller")), "--db", str(db), "users", "add", name, *operator],
        capture_output=True,
        text=True,
        check=True,
    )
    return made.stdout.strip()


def test_users_see_their_own_experiments_and_everyone_the_leaderboard(tmp_path: Path) -> None:
    db = tmp_path / "gym.db"
    alice, bob, ops = _add_user(db, "alice"), _add_user(db, "bob"), _add_user(db, "ops", "--operator")
    env_id = "sim/records-0"
    proc, endpoint = start_controller(tmp_path, env_id)
    try:
        env = gymnasium.make(
            "OffWorldMonolithDiscreteSim-v0",
            connect=endpoint,
            env_id=env_id,
            token=alice,
            experiment_name="eval",
            algorithm_mode="test",
            resolution=(12, 16),
        )
        try:
            steps, total, ended = _play(env, 5, 200)
            experiment_id = env.unwrapped.experiment_id
        finally:
            env.close()
        assert ended, "an episode ends within the step limit"

        (mine,) = offworld_gym.experiments(env_id, token=alice, connect=endpoint)
        assert (mine["id"], mine["name"], mine["user"], mine["episodes"], mine["steps"]) == (
            experiment_id,
            "eval",
            "alice",
            1,
            steps,
        )
        assert offworld_gym.experiments(env_id, token=bob, connect=endpoint) == []
        assert offworld_gym.experiments(env_id, token=ops, connect=endpoint) == [mine]
        shown, episodes = offworld_gym.experiment(env_id, experiment_id, token=alice, connect=endpoint)
        assert shown == mine
        assert [(e["index"], e["seed"], e["steps"], e["episode_return"]) for e in episodes] == [(0, 5, steps, total)]
        assert episodes[0]["recordings"] == []  # this controller does not record
        with pytest.raises(errors.NotFound, match="no experiment") as refused_show:
            offworld_gym.experiment(env_id, experiment_id, token=bob, connect=endpoint)
        assert refused_show.value.code == 404
        assert isinstance(refused_show.value, errors.OffWorldGymError)
        with pytest.raises(errors.Unauthorized):
            offworld_gym.experiments(env_id, token="not-a-token", connect=endpoint)

        (ranked,) = offworld_gym.leaderboard(env_id, connect=endpoint)
        assert (ranked["rank"], ranked["experiment"], ranked["user"], ranked["episodes"]) == (1, "eval", "alice", 1)
        assert ranked["mean_return"] == total
        assert ranked["success_rate"] == (1.0 if total > 0 else 0.0)

        # The same from the command line.
        def cli(*args: str, token: str | None = None) -> subprocess.CompletedProcess[str]:
            environment = dict(os.environ)
            if token is not None:
                environment["OFFWORLD_GYM_ACCESS_TOKEN"] = token
            return subprocess.run(
                [sys.executable, "-m", "offworld_gym", *args, "--env", env_id, "--connect", endpoint],
                capture_output=True,
                text=True,
                env=environment,
            )

        board = cli("leaderboard", "--json")
        assert board.returncode == 0, board.stderr
        assert json.loads(board.stdout) == [ranked]
        table = cli("episodes", "--id", str(experiment_id), token=alice)
        assert table.returncode == 0, table.stderr
        assert "experiment" in table.stdout and "'eval' of alice" in table.stdout
        refused = cli("episodes", "--id", str(experiment_id), token=bob)
        assert refused.returncode == 1
        assert "no experiment" in refused.stderr
    finally:
        stop(proc)
