"""Fixtures: a standalone deployment (the env_controller binary with
embedded twins) on a free loopback port, for tests that need a second
process or a remote connection."""

from __future__ import annotations

import os
import random
import socket
import subprocess
import time
from pathlib import Path

import pytest


def _free_port() -> int:
    """A free port below Linux's ephemeral range (32768-60999), so no
    connection's local port can take it before the controller listens."""
    rng = random.SystemRandom()
    for _ in range(64):
        port = rng.randrange(20000, 32000)
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError("no free loopback port in 20000-32000")


def _binary(name: str) -> Path:
    target = Path(os.environ.get("CARGO_TARGET_DIR", Path.home() / ".cache/offworld-target"))
    path = target / "release" / name
    if not path.exists():
        pytest.fail(f"{path} is missing: build it with `cargo build --release` (bash .ci/test does)")
    return path


def start_controller(tmp_path: Path, env_id: str, *extra: str) -> tuple[subprocess.Popen, str]:
    """Starts `offworld serve` with embedded twins for `env_id` on a free
    loopback port; returns the process and its endpoint once it listens."""
    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = subprocess.Popen(
        [
            str(_binary("offworld")),
            "--db",
            str(tmp_path / "gym.db"),
            "serve",
            "--env",
            f"{env_id}=MonolithDiscrete",
            "--embedded-twins",
            "--listen",
            endpoint,
            *extra,
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    # Bounded wait for the port to accept connections.
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"offworld serve exited: {proc.stderr.read().decode() if proc.stderr else ''}")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return proc, endpoint
        time.sleep(0.1)
    proc.kill()
    raise RuntimeError("env_controller did not start listening")


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()


@pytest.fixture()
def deployment(tmp_path: Path):
    """Yields (endpoint, env_id) of a sim deployment in another process."""
    env_id = "sim/contended-0"
    proc, endpoint = start_controller(tmp_path, env_id)
    try:
        yield endpoint, env_id
    finally:
        stop(proc)
