"""Save a learning curve PNG from an SB3 Monitor CSV, or from a fresh run of
random episodes when no CSV is given:

    python py_client/examples/plot_learning_curve.py --episodes 20 --out curve.png
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path


def plot(monitor_csv: Path, out: Path) -> None:
    """Episode returns (and their moving average) from a Monitor CSV."""
    with open(monitor_csv) as f:
        rows = [r for r in csv.reader(f) if r and not r[0].startswith("#")]
    returns = [float(r[0]) for r in rows[1:]]
    save(returns, out)


def save(returns: list[float], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    window = max(1, len(returns) // 10)
    smooth = [sum(returns[max(0, i - window + 1) : i + 1]) / len(returns[max(0, i - window + 1) : i + 1]) for i in range(len(returns))]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(returns, ".", alpha=0.4, label="episode return")
    ax.plot(smooth, "-", label=f"mean of {window}")
    ax.set_xlabel("episode")
    ax.set_ylabel("return")
    ax.set_title("OffWorld Monolith")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    print(f"wrote {out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--monitor", type=Path)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--out", type=Path, default=Path("learning_curve.png"))
    args = parser.parse_args()
    if args.monitor:
        plot(args.monitor, args.out)
        return
    import gymnasium

    import offworld_gym  # noqa: F401

    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", resolution=(84, 84))
    env.action_space.seed(0)
    returns = []
    env.reset(seed=0)
    for _ in range(args.episodes):
        total, done = 0.0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total += reward
            done = terminated or truncated
        returns.append(total)
        env.reset()
    env.close()
    save(returns, args.out)


if __name__ == "__main__":
    main()
