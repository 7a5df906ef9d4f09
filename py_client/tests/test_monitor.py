"""`rerun=`: the embedded env records itself to an .rrd that the rerun SDK
(rerun-sdk==0.36.3, installed by .ci/setup) reads back."""

from __future__ import annotations

import subprocess
import sys
from collections import Counter
from pathlib import Path

import gymnasium
import pytest
from rerun.experimental import RrdReader

from offworld_gym import errors
from offworld_gym.envs.common.channels import Channels

FORWARD, LEFT = 2, 0


def _rows_per_entity(path: Path) -> tuple[Counter[str], Counter[str]]:
    """(temporal rows, static rows) per entity path."""
    temporal: Counter[str] = Counter()
    static: Counter[str] = Counter()
    for chunk in RrdReader(str(path)).stream():
        (static if chunk.is_static else temporal)[chunk.entity_path] += chunk.num_rows
    return temporal, static


def _env_root(entities: Counter[str]) -> str:
    roots = {"/".join(e.split("/")[:4]) for e in entities if e.startswith("/envs/sim/")}
    assert len(roots) == 1, roots
    return roots.pop()


def test_rerun_records_every_frame_pose_command_and_reward(tmp_path):
    path = tmp_path / "run.rrd"
    env = gymnasium.make(
        "OffWorldMonolithDiscreteSim-v0", channel_type=Channels.RGBD, resolution=(84, 84), rerun=str(path)
    )
    resets, steps, rewards, finished = 0, 0, 0.0, 0
    for seed in (3, 4):
        env.reset(seed=seed)
        resets += 1
        for action in (FORWARD, LEFT, FORWARD, FORWARD, LEFT):
            _, reward, terminated, truncated, _ = env.step(action)
            steps += 1
            rewards += reward
            if terminated or truncated:
                finished += 1
                break
    env.close()
    assert path.stat().st_size > 0

    verify = subprocess.run(
        [sys.executable, "-m", "rerun", "rrd", "verify", str(path)], capture_output=True, text=True, timeout=300
    )
    assert verify.returncode == 0, verify.stdout + verify.stderr

    temporal, static = _rows_per_entity(path)
    root = _env_root(temporal)
    answered = resets + steps  # every reset and step is one command answered by one frame and pose
    for entity in ("robot", "odom/robot", "robot/camera/color", "robot/camera/depth", "metrics/linear_x"):
        assert temporal[f"{root}/{entity}"] == answered, (entity, temporal)
    assert temporal[f"{root}/metrics/reward"] == answered, temporal
    for entity in ("world/walls", "world/monolith", "world/success_radius", "robot/body", "robot/camera"):
        assert static[f"{root}/{entity}"] >= 1, (entity, static)
    assert temporal[f"{root}/events"] >= 2 * resets  # episode starts and ends
    assert temporal[f"{root}/metrics/success"] == finished


def test_a_bad_rerun_sink_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="expected a .rrd path"):
        gymnasium.make("OffWorldMonolithDiscreteSim-v0", rerun=str(tmp_path / "run.txt"))
    with pytest.raises(errors.OffWorldGymError, match="monitor"):
        gymnasium.make("OffWorldMonolithDiscreteSim-v0", rerun=str(tmp_path / "missing-dir" / "run.rrd"))
