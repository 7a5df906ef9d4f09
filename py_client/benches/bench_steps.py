"""Python steps/s against the Rust-only rate, measured in one run.

    python py_client/benches/bench_steps.py                 # 84x84 depth uint8
    python py_client/benches/bench_steps.py --rgbd-320x240  # 320x240 RGBD uint8

Rust-only: the `client_steps` example (same embedded stack, same actions),
one env and a `VecEnvClient` of 2. Python: one embedded env via
gymnasium.make, and make_vec with 2 envs.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import gymnasium
import numpy as np

import offworld_gym  # noqa: F401
from offworld_gym.envs.common.channels import Channels

STEPS = 1000
ROUNDS = 5
RGBD = "--rgbd-320x240" in sys.argv[1:]
H, W = (240, 320) if RGBD else (84, 84)
OPTIONS = {"resolution": (H, W), "channel_type": Channels.RGBD if RGBD else Channels.DEPTH_ONLY}


def python_single() -> float:
    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", **OPTIONS)
    env.reset(seed=0)
    start = time.perf_counter()
    for i in range(STEPS):
        _, _, terminated, truncated, _ = env.step(i % 4)
        if terminated or truncated:
            env.reset()
    rate = STEPS / (time.perf_counter() - start)
    env.close()
    return rate


def python_vec(n: int) -> float:
    envs = gymnasium.make_vec("OffWorldMonolithDiscreteSim-v0", num_envs=n, **OPTIONS)
    envs.reset(seed=0)
    start = time.perf_counter()
    for i in range(STEPS // n):
        envs.step(np.full(n, i % 4))
    rate = (STEPS // n) * n / (time.perf_counter() - start)
    envs.close()
    return rate


def rust_only(envs: int = 1) -> float:
    target = Path(os.environ.get("CARGO_TARGET_DIR", Path.home() / ".cache/offworld-target"))
    binary = target / "release/examples/client_steps"
    args = [str(binary), str(W), str(H), str(STEPS), *(["rgbd"] if RGBD else []), f"envs={envs}"]
    out = subprocess.run(args, capture_output=True, text=True, check=True)
    return float(out.stdout.split()[-1])


def main() -> None:
    # Interleaved rounds, medians: run-to-run noise on 2 shared cores is large.
    rounds = [(rust_only(), rust_only(2), python_single(), python_vec(2)) for _ in range(ROUNDS)]
    rust, rust_vec2, single, vec2 = (float(np.median([r[i] for r in rounds])) for i in range(4))
    observation = "RGBD" if RGBD else "depth"
    print(f"{W}x{H} {observation} uint8, {STEPS} steps, embedded sim, 2 cores, medians of {ROUNDS} interleaved rounds:")
    print(f"  rust-only (EnvClient)          : {rust:7.0f} steps/s")
    print(f"  rust-only VecEnvClient of 2    : {rust_vec2:7.0f} steps/s  ({rust_vec2 / rust:.2f}x one env)")
    print(f"  python gymnasium.make          : {single:7.0f} steps/s  (python layer costs {100 * (1 - single / rust):.1f} %)")
    print(f"  python make_vec(num_envs=2)    : {vec2:7.0f} steps/s  ({vec2 / single:.2f}x one env)")


if __name__ == "__main__":
    main()
