"""Through the real zenohd router with the repository's deployment files
(QUIC with TLS 1.3, passwords, ACL): a sim farm of two twin processes and a
gym server (`offworld farm`). Discovery, vector envs across processes,
bookings from Python and the CLI."""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
import threading
import time

import gymnasium
import numpy as np
import pytest

import offworld_gym
from conftest import _binary
from offworld_gym import errors


@pytest.fixture(scope="module")
def farm():
    """Yields (environment for a trainer, env ids) of a running sim farm."""
    proc = subprocess.Popen(
        [str(_binary("offworld")), "farm", "--twins", "2"],
        stdout=subprocess.PIPE,
        text=True,
    )
    env: dict[str, str] = {}
    assert proc.stdout is not None
    deadline = time.monotonic() + 120
    # How to connect, as KEY=VALUE lines; the farm's env list comes last.
    for line in proc.stdout:
        key, _, value = line.strip().partition("=")
        env[key] = value
        if key == "OFFWORLD_FARM_ENVS":
            break
        assert time.monotonic() < deadline, "offworld farm did not come up"
    else:
        pytest.fail(f"offworld farm exited: {proc.wait()}")
    yield env, env["OFFWORLD_FARM_ENVS"].split(",")
    proc.terminate()  # SIGTERM: the farm stops its processes and router
    assert proc.wait(timeout=60) == 0


@pytest.fixture()
def trainer(farm, monkeypatch):
    """The trainer's environment (role file, certificate, password, token)."""
    env, envs = farm
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    return envs


def test_list_envs_shows_each_env_with_task_state_and_components(trainer):
    listed = offworld_gym.list_envs()
    assert [e["env_id"] for e in listed] == trainer
    for e in listed:
        assert e["task"] == "MonolithDiscrete"
        assert e["state"] == "free", e
        assert e["components"] == ["controller", "sim_twin"]
        assert e["estops"] == {}, "no e-stop engaged"
        assert e["who"] is None and e["until_unix_ms"] is None, e
    # The same through the CLI, as JSON.
    out = subprocess.run(
        [sys.executable, "-m", "offworld_gym", "envs", "--json"], capture_output=True, text=True, check=True
    )
    assert [e["env_id"] for e in json.loads(out.stdout)] == trainer


def test_make_vec_by_discovery_steps_twins_in_separate_processes(trainer):
    """Two twin processes stepped together through the router (QUIC, mTLS,
    ACL), by discovery and by id list."""
    twin_processes = trainer
    envs = gymnasium.make_vec(
        "OffWorldMonolithDiscreteSim-v0", num_envs=2, env_id="discover", resolution=(84, 84)
    )
    try:
        obs, _ = envs.reset(seed=5)
        assert obs.shape == (2, 84, 84, 1)
        # Both leased now: discovery says so.
        listed = offworld_gym.list_envs()
        assert {e["env_id"]: e["state"] for e in listed} == {env_id: "leased" for env_id in twin_processes}
        # The trainer fixture signs in as alice (OFFWORLD_GYM_ACCESS_TOKEN).
        assert all(e["who"] == "alice" and e["until_unix_ms"] > 0 for e in listed), listed
        for _ in range(5):
            obs, rewards, terminated, truncated, info = envs.step(np.array([2, 2]))
        assert list(info["step"]) == [5, 5]
    finally:
        envs.close()
    # By id list as well.
    envs = gymnasium.make_vec(
        "OffWorldMonolithDiscreteSim-v0", num_envs=2, env_id=list(reversed(twin_processes)), resolution=(84, 84)
    )
    envs.reset(seed=1)
    envs.close()


def test_discovery_refuses_more_envs_than_are_free(trainer):
    with pytest.raises(errors.NotFound, match="3 free") as refused:
        gymnasium.make_vec("OffWorldMonolithDiscreteSim-v0", num_envs=3, env_id="discover")
    # The error names the envs that do exist, so the fix is in the message.
    message = str(refused.value)
    assert "envs reachable here:" in message
    for env_id in trainer:
        assert f"{env_id} (MonolithDiscrete, free)" in message, message


def test_a_leased_env_is_waited_for_in_line(trainer, capfd):
    """`wait=`: instead of Busy at once, the client waits in the env's line
    (saying its place on stderr) and gets the env when the lease ends."""
    env_id = trainer[1]
    make = functools.partial(gymnasium.make, "OffWorldMonolithDiscreteSim-v0", env_id=env_id, resolution=(12, 16))
    holder = make()  # alice
    opened: dict[str, object] = {}

    def wait_in_line() -> None:
        try:
            opened["env"] = make(token="", wait=60)
        except Exception as e:  # noqa: BLE001 - reported by the test below
            opened["error"] = e

    waiter = threading.Thread(target=wait_in_line, daemon=True)
    try:
        # Another user (anonymous, allowed on sim envs) who does not wait is refused at once.
        with pytest.raises(errors.Busy, match="is leased by another user until"):
            make(token="")
        waiter.start()
        said = ""
        deadline = time.monotonic() + 30
        while "1st in line; waiting (up to 60 s)" not in said:
            assert time.monotonic() < deadline, f"the waiter never said its place: {said!r} {opened}"
            time.sleep(0.2)
            said += capfd.readouterr().err
        assert f"offworld_gym: {env_id} is leased by another user until" in said, said
        assert waiter.is_alive(), "still waiting while alice holds the env"
    finally:
        holder.close()
        waiter.join(timeout=30)
    assert not waiter.is_alive(), "the waiter got the env once alice closed hers"
    assert "error" not in opened, opened
    env = opened["env"]
    try:
        obs, _ = env.reset(seed=1)
        assert obs.shape == (12, 16, 1)
        listed = {e["env_id"]: e for e in offworld_gym.list_envs()}
        assert listed[env_id]["who"] == "anonymous", listed[env_id]
    finally:
        env.close()


def test_bookings_from_python_and_the_cli(trainer):
    env_id = trainer[0]
    start = time.time() + 3600
    made = offworld_gym.book(env_id, start, start + 1800)
    assert made["env_id"] == env_id and made["user"] == "alice"
    assert made["end_unix_ms"] - made["start_unix_ms"] == 1_800_000
    with pytest.raises(errors.Busy, match="booked by alice"):
        offworld_gym.book(env_id, start + 600, start + 900)
    with pytest.raises(errors.BadRequest):
        offworld_gym.book(env_id, start, start - 60)
    listed = offworld_gym.bookings(env_id)
    assert made in listed
    cli = subprocess.run(
        [sys.executable, "-m", "offworld_gym", "bookings", "--env", env_id, "--json"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert made in json.loads(cli.stdout)
    # Discovery shows the slot on its env, and only there.
    slots = {e["env_id"]: e["bookings"] for e in offworld_gym.list_envs()}
    assert slots == {env_id: [made], trainer[1]: []}
    table = subprocess.run(
        [sys.executable, "-m", "offworld_gym", "envs"], capture_output=True, text=True, check=True
    ).stdout
    assert "booked by alice" in table
    # Who the token is, and her slots on every env.
    assert offworld_gym.whoami() == {"user": "alice", "operator": False}
    assert offworld_gym.whoami(env_id=trainer[1]) == {"user": "alice", "operator": False}
    with pytest.raises(errors.Unauthorized, match="unknown access token"):
        offworld_gym.whoami(token="not-a-token-of-anyone")
    assert offworld_gym.my_bookings() == [made]
    cli = subprocess.run(
        [sys.executable, "-m", "offworld_gym", "bookings", "--mine", "--json"], capture_output=True, text=True, check=True
    )
    assert json.loads(cli.stdout) == [made]
    who = subprocess.run([sys.executable, "-m", "offworld_gym", "whoami"], capture_output=True, text=True, check=True)
    assert who.stdout == "alice\n"
    remaining = offworld_gym.cancel_booking(env_id, made["id"])
    assert made not in remaining
    assert all(e["bookings"] == [] for e in offworld_gym.list_envs())
    assert offworld_gym.my_bookings() == []
    empty = subprocess.run(
        [sys.executable, "-m", "offworld_gym", "bookings", "--mine"], capture_output=True, text=True, check=True
    )
    assert (empty.stdout, empty.stderr) == ("", "nothing booked\n")
    # `bookings` needs an env or --mine.
    neither = subprocess.run([sys.executable, "-m", "offworld_gym", "bookings"], capture_output=True, text=True)
    assert neither.returncode == 2 and "<--env <ENV_ID>|--mine>" in neither.stderr
    # Without a token: a clear error before anything is sent.
    with pytest.raises(errors.ConfigurationError, match="token"):
        offworld_gym.book(env_id, start, start + 60, token="")
