"""Train DQN (Stable-Baselines3) on depth-only 84×84 observations and save
the learning curve. Not run in CI (it needs torch and hours):

    pip install stable-baselines3 matplotlib
    python py_client/examples/train_dqn.py --steps 50000 --out runs/dqn
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium

import offworld_gym  # noqa: F401
from offworld_gym.envs.common.channels import Channels


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="OffWorldMonolithDiscreteSim-v0")
    parser.add_argument("--steps", type=int, default=50_000)
    parser.add_argument("--out", type=Path, default=Path("runs/dqn"))
    args = parser.parse_args()

    from stable_baselines3 import DQN
    from stable_baselines3.common.monitor import Monitor

    args.out.mkdir(parents=True, exist_ok=True)
    env = Monitor(
        gymnasium.make(args.env, channel_type=Channels.DEPTH_ONLY, resolution=(84, 84), experiment_name="dqn-depth"),
        str(args.out / "monitor"),
    )
    model = DQN("CnnPolicy", env, buffer_size=50_000, learning_starts=1_000, exploration_fraction=0.3, verbose=1)
    model.learn(total_timesteps=args.steps)
    model.save(args.out / "model")
    env.close()

    from plot_learning_curve import plot

    plot(args.out / "monitor.monitor.csv", args.out / "learning_curve.png")


if __name__ == "__main__":
    main()
