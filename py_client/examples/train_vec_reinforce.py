"""Train a policy on N envs at once with ``gymnasium.make_vec`` — numpy
only, no deep-learning framework: REINFORCE with a baseline, a linear
softmax policy over the depth image pooled to a coarse grid. It shows the
vector API and gymnasium's next-step autoreset (an env whose episode ended
is reset by the next ``step``, whose action it ignores); swap in your own
learner where ``update`` is.

    python py_client/examples/train_vec_reinforce.py                                  # 2 envs, 100 iterations
    python py_client/examples/train_vec_reinforce.py --num-envs 4 --env-id discover   # free twins of a sim farm
    python py_client/examples/train_vec_reinforce.py --out runs/reinforce             # progress.csv + policy.npz

On the embedded twin (MonolithDiscrete, 24×32 depth, seed 0) the robot
reaches the monolith in ~50 % of the episodes of the first 20 iterations
(learning starts at once at the default learning rate) and ~90 % of the
last 20 (51,200 steps, ~30 s on 2 cores). A seed gives
the same run, line for line (the twins are deterministic).
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import gymnasium
import numpy as np

import offworld_gym  # noqa: F401  (registers the ids)
from offworld_gym.envs.common.channels import Channels

#: The depth image is mean-pooled to this grid (rows, columns).
GRID = (4, 8)


def features(obs: np.ndarray) -> np.ndarray:
    """(N, H, W, 1) uint8 depth → (N, rows·cols + 1): pooled, scaled to [0, 1], plus a bias."""
    n, h, w, _ = obs.shape
    rows, cols = GRID
    pooled = obs[:, : h - h % rows, : w - w % cols, 0].reshape(n, rows, h // rows, cols, w // cols).mean(axis=(2, 4))
    return np.concatenate([pooled.reshape(n, -1) / 255.0, np.ones((n, 1))], axis=1)


def policy(weights: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Action probabilities, (N, actions)."""
    logits = x @ weights
    logits -= logits.max(axis=1, keepdims=True)
    p = np.exp(logits)
    return p / p.sum(axis=1, keepdims=True)


def update(weights: np.ndarray, episodes: list[list[tuple[np.ndarray, int, float]]], gamma: float, lr: float) -> None:
    """REINFORCE: each step's log-probability gradient times its return minus the batch's mean return."""
    returns = []
    for episode in episodes:
        g, gs = 0.0, []
        for _, _, reward in reversed(episode):
            g = reward + gamma * g
            gs.append(g)
        returns.append(gs[::-1])
    baseline = np.mean([g for gs in returns for g in gs])
    gradient = np.zeros_like(weights)
    for episode, gs in zip(episodes, returns):
        for (x, action, _), g in zip(episode, gs):
            p = policy(weights, x[None])[0]
            grad_log = -p
            grad_log[action] += 1.0
            gradient += np.outer(x, grad_log) * (g - baseline)
    weights += lr * gradient / max(1, sum(len(e) for e in episodes))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="OffWorldMonolithDiscreteSim-v0", help="gymnasium id (discrete actions)")
    parser.add_argument("--env-id", metavar="REALM/NAME", help="as make_vec's env_id: 'discover' takes free envs of a deployment")
    parser.add_argument("--num-envs", type=int, default=2, help="envs stepped at once")
    parser.add_argument("--iterations", type=int, default=100, help="policy updates")
    parser.add_argument("--steps-per-iteration", type=int, default=256, help="vector steps between updates")
    parser.add_argument("--lr", type=float, default=20.0, help="learning rate")
    parser.add_argument("--gamma", type=float, default=0.99, help="discount")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution", type=int, nargs=2, default=(24, 32), metavar=("H", "W"), help="observation size")
    parser.add_argument("--out", type=Path, help="write progress.csv and policy.npz here")
    args = parser.parse_args()
    if args.num_envs < 1 or args.iterations < 1 or args.steps_per_iteration < 1:
        parser.error("--num-envs, --iterations and --steps-per-iteration must be at least 1")
    if args.resolution[0] < GRID[0] or args.resolution[1] < GRID[1]:
        parser.error(f"--resolution must be at least {GRID[0]} {GRID[1]} (the policy pools the image to that grid)")

    options = {"env_id": args.env_id} if args.env_id else {}
    envs = gymnasium.make_vec(
        args.env,
        num_envs=args.num_envs,
        channel_type=Channels.DEPTH_ONLY,
        resolution=tuple(args.resolution),
        experiment_name="vec-reinforce",
        **options,
    )
    rng = np.random.default_rng(args.seed)
    actions = envs.single_action_space.n
    weights = np.zeros((GRID[0] * GRID[1] + 1, actions))
    obs, _ = envs.reset(seed=args.seed)
    # Next-step autoreset: after an env's episode ends, its next step only resets it.
    resetting = np.zeros(args.num_envs, dtype=bool)
    running: list[list[tuple[np.ndarray, int, float]]] = [[] for _ in range(args.num_envs)]
    progress = []
    started = time.perf_counter()
    total_steps = 0
    for iteration in range(args.iterations):
        finished: list[list[tuple[np.ndarray, int, float]]] = []
        successes = 0
        for _ in range(args.steps_per_iteration):
            x = features(obs)
            p = policy(weights, x)
            chosen = np.array([rng.choice(actions, p=row) for row in p])
            obs, rewards, terminated, truncated, info = envs.step(chosen)
            total_steps += args.num_envs
            for i in range(args.num_envs):
                if resetting[i]:
                    continue  # this step was the reset: no transition
                running[i].append((x[i], int(chosen[i]), float(rewards[i])))
                if terminated[i] or truncated[i]:
                    finished.append(running[i])
                    successes += bool(info["is_success"][i])
                    running[i] = []
            resetting = terminated | truncated
        if finished:
            update(weights, finished, args.gamma, args.lr)
        mean_return = float(np.mean([sum(r for _, _, r in e) for e in finished])) if finished else 0.0
        success_rate = successes / len(finished) if finished else 0.0
        progress.append((iteration, len(finished), mean_return, success_rate, total_steps))
        print(
            f"iteration {iteration}: {len(finished)} episodes, mean return {mean_return:.3f}, "
            f"success {100 * success_rate:.0f}%, {total_steps} steps"
        )
    elapsed = time.perf_counter() - started
    envs.close()
    print(f"{total_steps} steps in {elapsed:.2f} s ({total_steps / elapsed:.0f} steps/s over {args.num_envs} envs)")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        with open(args.out / "progress.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["iteration", "episodes", "mean_return", "success_rate", "steps"])
            writer.writerows(progress)
        np.savez(args.out / "policy.npz", weights=weights, grid=np.array(GRID))
        print(f"wrote {args.out / 'progress.csv'} and {args.out / 'policy.npz'}")


if __name__ == "__main__":
    main()
