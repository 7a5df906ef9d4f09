"""`OffWorldMonolithDiscreteReal-v0` through gymnasium against the emulated
enclosure: env_controller + robot_agent + tracker_agent as processes under
`real/monolith-0`, driving `offworld emulate-hardware` in real time
(started by `offworld emulate-enclosure`)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from conftest import _binary

AGENT = textwrap.dedent(
    """
    import gymnasium, numpy as np, offworld_gym
    from offworld_gym.envs.common.channels import Channels
    from offworld_gym.envs.common.enums import AlgorithmMode, LearningType

    def make_env(attempt):
        return gymnasium.make(
            "OffWorldMonolithDiscreteReal-v0",
            experiment_name="emulated-py",
            resume_experiment=attempt > 0,
            learning_type=LearningType.END_TO_END,
            algorithm_mode=AlgorithmMode.TRAIN,
            channel_type=Channels.DEPTH_ONLY,
            resolution=(84, 84),
        )

    # A real deployment's typed transient errors (a starved host loses a
    # frame or the tracker for a moment) end the attempt; the script starts
    # over with a fresh env, as a training loop on a real robot does
    # (gymnasium's passive checker cannot step an env whose first reset
    # raised).
    env = None
    for attempt in range(3):
        if env is not None:
            env.close()
        env = make_env(attempt)
        try:
            obs, info = env.reset(seed=7)  # the robot agent drives to the spawn pose
            assert obs.shape == (84, 84, 1) and obs.dtype == np.uint8, obs.shape
            assert 0 < int(obs.max()) <= 255
            total = 0
            for step in range(1, 4):
                obs, reward, terminated, truncated, info = env.step(step % 2)  # LEFT / RIGHT turns stay inside
                assert info["step"] == step, info
                # Real envs keep the ground truth to themselves by default.
                assert "pose" not in info and "distance_to_goal" not in info, info
                assert not truncated
                total += 1
            break
        except (offworld_gym.errors.Timeout, offworld_gym.errors.Unavailable, offworld_gym.errors.InvalidState) as e:
            print("attempt", attempt, "ended by", type(e).__name__, e)
    else:
        raise SystemExit("three attempts ended by transient errors")
    env.close()
    print("real steps", total)
    """
)


def test_real_id_trains_against_the_emulated_enclosure() -> None:
    result = subprocess.run(
        [
            str(_binary("offworld")),
            "emulate-enclosure",
            "--task",
            "MonolithDiscrete",
            # This test is about the gym API on a real id; a wider watchdog
            # window keeps a CPU-starved CI machine from braking the reset drive.
            "--watchdog-ms",
            "500",
            "--",
            sys.executable,
            "-c",
            AGENT,
        ],
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert result.returncode == 0, result.stderr[-3000:] + result.stdout[-2000:]
    assert "real steps 3" in result.stdout
