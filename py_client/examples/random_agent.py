"""A random agent on the embedded sim (no router, no robot needed), or on
any deployment named by OFFWORLD_GYM_CONNECT / OFFWORLD_GYM_ACCESS_TOKEN.

    python py_client/examples/random_agent.py --episodes 3
    python py_client/examples/random_agent.py --env OffWorldMonolithDiscreteReal-v0 --max-steps 20
    python py_client/examples/random_agent.py --env OffWorldMonolithDiscreteSim-v0 --env-id sim/farm-2
    python py_client/examples/random_agent.py --episodes 10 --record runs/   # MCAP per episode
"""

from __future__ import annotations

import argparse
import time

import gymnasium

import offworld_gym  # noqa: F401  (registers the ids)
from offworld_gym.envs.common.channels import Channels


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--env", default="OffWorldMonolithDiscreteSim-v0", help="gymnasium id")
    parser.add_argument(
        "--env-id",
        metavar="REALM/NAME",
        help="which env of a deployment (default: <realm>/<world>-0, or OFFWORLD_GYM_ENV); 'discover' takes any free one",
    )
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-steps", type=int, default=0, help="stop after this many steps in all (0 = no limit)")
    parser.add_argument(
        "--record", metavar="DIR", help="record every episode as an MCAP file under DIR (embedded sim envs)"
    )
    parser.add_argument(
        "--resolution", type=int, nargs=2, default=(240, 320), metavar=("H", "W"), help="observation size"
    )
    args = parser.parse_args()

    started = time.perf_counter()
    options = {"record": args.record} if args.record else {}
    if args.env_id:
        options["env_id"] = args.env_id
    # Recordings keep colour and depth whatever the agent sees.
    channels = Channels.RGBD if args.record else Channels.DEPTH_ONLY
    env = gymnasium.make(args.env, channel_type=channels, resolution=tuple(args.resolution), **options)
    obs, info = env.reset(seed=args.seed)
    print(f"{args.env}: first observation {obs.shape} {obs.dtype} after {1000 * (time.perf_counter() - started):.0f} ms")
    env.action_space.seed(args.seed)
    steps = 0
    loop_start = time.perf_counter()
    for episode in range(args.episodes):
        episode_return, done = 0.0, False
        while not done and not (args.max_steps and steps >= args.max_steps):
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            episode_return += reward
            steps += 1
            done = terminated or truncated
        if not done:
            print(f"episode {episode}: stopped after {info['step']} steps (--max-steps)")
            break
        outcome = "reached the monolith" if terminated and reward > 0 else ("left the arena" if terminated else "time limit")
        print(f"episode {episode}: return {episode_return:.0f} in {info['step']} steps ({outcome})")
        if episode + 1 < args.episodes:
            obs, info = env.reset()
    elapsed = time.perf_counter() - loop_start
    print(f"{steps} steps in {elapsed:.2f} s ({steps / elapsed:.0f} steps/s)")
    env.close()


if __name__ == "__main__":
    main()
