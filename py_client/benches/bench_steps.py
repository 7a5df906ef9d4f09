"""Python steps/s against the Rust-only rate, measured in one run.

    python py_client/benches/bench_steps.py

Rust-only: the `client_steps` example (same embedded stack, same actions).
Python: one embedded env via gymnasium.make, and make_vec with 2 envs.
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import gymnasium
import numpy as np

import offworld_gym  # noqa: F401

STEPS = 1000
ROUNDS = 5
H = W = 84


def python_single() -> float:
    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", resolution=(H, W))
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
    envs = gymnasium.make_vec("OffWorldMonolithDiscreteSim-v0", num_envs=n, resolution=(H, W))
    envs.reset(seed=0)
    start = time.perf_counter()
    for i in range(STEPS // n):
        envs.step(np.full(n, i % 4))
    rate = (STEPS // n) * n / (time.perf_counter() - start)
    envs.close()
    return rate


def rust_only() -> float:
    target = Path(os.environ.get("CARGO_TARGET_DIR", Path.home() / ".cache/offworld-target"))
    binary = target / "release/examples/client_steps"
    out = subprocess.run([str(binary), str(W), str(H), str(STEPS)], capture_output=True, text=True, check=True)
    return float(out.stdout.split()[-1])


def main() -> None:
    # Interleaved rounds, medians: run-to-run noise on 2 shared cores is large.
    rounds = [(rust_only(), python_single(), python_vec(2)) for _ in range(ROUNDS)]
    rust, single, vec2 = (float(np.median([r[i] for r in rounds])) for i in range(3))
    print(f"{H}x{W} depth uint8, {STEPS} steps, embedded sim, 2 cores, medians of {ROUNDS} interleaved rounds:")
    print(f"  rust-only (EnvClient)          : {rust:7.0f} steps/s")
    print(f"  python gymnasium.make          : {single:7.0f} steps/s  (python layer costs {100 * (1 - single / rust):.1f} %)")
    print(f"  python make_vec(num_envs=2)    : {vec2:7.0f} steps/s  ({vec2 / single:.2f}x one env)")


if __name__ == "__main__":
    main()
