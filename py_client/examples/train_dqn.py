"""Train DQN (Stable-Baselines3) on depth-only 84×84 observations and save
the learning curve. Not run in CI (it needs torch and hours):

    pip install stable-baselines3 matplotlib
    python py_client/examples/train_dqn.py --steps 50000 --out runs/dqn
    python py_client/examples/train_dqn.py --env-id discover --learning-rate 5e-4 --seed 3

Without a deep-learning framework, on several envs at once:
train_vec_reinforce.py.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium

import offworld_gym  # noqa: F401
from offworld_gym.envs.common.channels import Channels


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="OffWorldMonolithDiscreteSim-v0", help="gymnasium id (discrete actions)")
    parser.add_argument("--env-id", metavar="REALM/NAME", help="which env of a deployment; 'discover' takes a free one")
    parser.add_argument("--steps", type=int, default=50_000, help="environment steps to train for")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution", type=int, nargs=2, default=(84, 84), metavar=("H", "W"), help="depth image size")
    parser.add_argument("--learning-rate", type=float, default=1e-4)
    parser.add_argument("--buffer-size", type=int, default=50_000, help="replay buffer, transitions")
    parser.add_argument("--learning-starts", type=int, default=1_000, help="steps before the first update")
    parser.add_argument("--exploration-fraction", type=float, default=0.3, help="share of --steps over which epsilon decays")
    parser.add_argument("--experiment-name", default="dqn-depth", help="the controller's experiment (resumable)")
    parser.add_argument("--device", default="auto", help="torch device: auto, cpu, cuda")
    parser.add_argument("--out", type=Path, default=Path("runs/dqn"), help="monitor CSV, model and learning curve")
    args = parser.parse_args()

    try:
        from stable_baselines3 import DQN
        from stable_baselines3.common.monitor import Monitor
    except ImportError:
        # For a framework-free start: train_vec_reinforce.py.
        parser.exit(2, "error: this example needs Stable-Baselines3: pip install stable-baselines3 matplotlib\n")

    args.out.mkdir(parents=True, exist_ok=True)
    options = {"env_id": args.env_id} if args.env_id else {}
    env = Monitor(
        gymnasium.make(
            args.env,
            channel_type=Channels.DEPTH_ONLY,
            resolution=tuple(args.resolution),
            experiment_name=args.experiment_name,
            **options,
        ),
        str(args.out / "monitor"),
    )
    model = DQN(
        "CnnPolicy",
        env,
        learning_rate=args.learning_rate,
        buffer_size=args.buffer_size,
        learning_starts=args.learning_starts,
        exploration_fraction=args.exploration_fraction,
        seed=args.seed,
        device=args.device,
        verbose=1,
    )
    model.learn(total_timesteps=args.steps)
    model.save(args.out / "model")
    env.close()

    from plot_learning_curve import plot

    plot(args.out / "monitor.monitor.csv", args.out / "learning_curve.png")


if __name__ == "__main__":
    main()
