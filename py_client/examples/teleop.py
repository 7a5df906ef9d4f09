"""Drive the robot by hand (or by script): w = forward, s = backward,
a = left, d = right, r = reset, q = quit. Keys come from stdin lines, so a
script can pipe them in:

    echo "wwwaawwd" | python py_client/examples/teleop.py

Episodes are human demonstrations (learning type HUMAN_DEMOS, listed by
`env_controller experiments list`). Recorded as MCAP files with --record DIR
on the embedded sim; a deployment records them with `serve --record`:

    python py_client/examples/teleop.py --record demos/ --experiment my-demos
"""

from __future__ import annotations

import argparse
import sys

import gymnasium

import offworld_gym  # noqa: F401
from offworld_gym.envs.common.channels import Channels
from offworld_gym.envs.common.enums import LearningType

KEYS = {"a": 0, "d": 1, "w": 2, "s": 3}  # LEFT, RIGHT, FORWARD, BACKWARD


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="OffWorldMonolithDiscreteSim-v0")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--experiment", default="", help="experiment name (default: a new one)")
    parser.add_argument("--record", metavar="DIR", help="record every episode under DIR (embedded sim envs)")
    args = parser.parse_args()
    options = {"record": args.record} if args.record else {}
    env = gymnasium.make(
        args.env,
        channel_type=Channels.DEPTH_ONLY,
        resolution=(84, 84),
        learning_type=LearningType.HUMAN_DEMOS,
        experiment_name=args.experiment,
        **options,
    )
    env.reset(seed=args.seed)
    print("keys: w/a/s/d move, r reset, q quit", file=sys.stderr)
    for line in sys.stdin:
        for key in line.strip().lower():
            if key == "q":
                env.close()
                return
            if key == "r":
                env.reset()
                print("reset")
                continue
            if key not in KEYS:
                continue
            obs, reward, terminated, truncated, info = env.step(KEYS[key])
            centre = int(obs[obs.shape[0] // 2, obs.shape[1] // 2, 0])
            print(f"{key}: step {info['step']} reward {reward:.0f} centre depth {centre}/255")
            if terminated or truncated:
                print("episode over:", "success" if reward > 0 else "terminated" if terminated else "time limit")
                env.reset()
    env.close()


if __name__ == "__main__":
    main()
