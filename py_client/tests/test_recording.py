"""Episodes recorded by embedded envs (``record=``), opened with the field's
own readers: ``mcap`` + ``mcap-ros2-support``, and ``rosbags`` (its
high-level ``AnyReader`` and the rosbag2 ``Reader`` with a ROS 2 Jazzy
typestore). Every message of every file is decoded; steps, actions,
rewards and images are compared with what the env returned."""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from conftest import _binary, start_controller, stop
from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.reader import make_reader
from mcap.records import Channel, Footer, Message
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

import offworld_gym  # noqa: F401  (registers the ids)
from offworld_gym.envs.common.channels import Channels
from offworld_gym.errors import ConfigurationError

#: Standard ROS 2 types in a recording: their schemas must be Jazzy's.
STANDARD = (
    "sensor_msgs/msg/Image",
    "geometry_msgs/msg/Twist",
    "geometry_msgs/msg/PoseStamped",
    "nav_msgs/msg/Odometry",
)

H, W = 24, 32


def _record(directory: Path, env_id: str, episodes: int, steps: int):
    """Runs `episodes` seeded episodes of up to `steps` random steps; returns
    per episode the list of (action, reward, terminated, truncated, obs)."""
    env = gymnasium.make(env_id, channel_type=Channels.RGBD, resolution=(H, W), record=directory)
    env.action_space.seed(3)
    runs = []
    try:
        for episode in range(episodes):
            obs, _ = env.reset(seed=episode)
            run = [(None, 0.0, False, False, obs)]
            for _ in range(steps):
                action = env.action_space.sample()
                obs, reward, terminated, truncated, _ = env.step(action)
                run.append((action, reward, terminated, truncated, obs))
                if terminated or truncated:
                    break
            runs.append(run)
    finally:
        env.close()
    return runs


def _files(directory: Path) -> list[Path]:
    return sorted(directory.rglob("*.mcap*"))


def test_every_message_decodes_with_mcap_and_rosbags_and_matches_the_env(tmp_path: Path):
    runs = _record(tmp_path, "OffWorldMonolithDiscreteSim-v0", episodes=3, steps=6)
    files = _files(tmp_path)
    assert [f.name for f in files] == ["ep-000000.mcap", "ep-000001.mcap", "ep-000002.mcap"]
    assert all(f.parent.name == files[0].parent.name for f in files), "one experiment"

    for path, run in zip(files, runs):
        # mcap + mcap-ros2-support: every message decodes against its schema.
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            assert reader.get_header().profile == "ros2"
            summary = reader.get_summary()
            meta = {m.name: m.metadata for m in reader.iter_metadata()}["offworld.episode"]
            decoded = list(reader.iter_decoded_messages())
        assert len(decoded) == summary.statistics.message_count
        assert meta["task"] == "MonolithDiscrete"
        assert meta["embodiment"] == "twin"
        assert int(meta["episode_id"]) == int(path.stem.removeprefix("ep-"))
        schemas = {s.name: s for s in summary.schemas.values()}
        for channel in summary.channels.values():
            assert channel.message_encoding == "cdr"
            assert schemas[summary.schemas[channel.schema_id].name].encoding == "ros2msg"
            assert "offered_qos_profiles" in channel.metadata

        # rosbags, types registered from the file's own schemas.
        by_topic: dict[str, list] = {}
        with AnyReader([path]) as bag:
            for conn, t_ns, raw in bag.messages():
                by_topic.setdefault(conn.topic, []).append((t_ns, bag.deserialize(raw, conn.msgtype)))
        assert sum(len(v) for v in by_topic.values()) == len(decoded)
        steps = [m for _, m in by_topic["/offworld/step"]]
        colors = [m for _, m in by_topic["/camera/color/image_raw"]]
        depths = [m for _, m in by_topic["/camera/depth/image_raw"]]
        assert len(steps) == len(colors) == len(depths) == len(run)
        assert len(by_topic["/cmd_vel"]) == len(run) - 1
        assert len(by_topic["/tracker/pose"]) == len(run)
        assert len(by_topic["/odom"]) >= len(run)
        [(_, info)] = by_topic["/offworld/episode"]
        assert (info.env_id, info.task, info.learning_type) == (meta["env_id"], "MonolithDiscrete", "end2end")
        assert info.seeded and info.seed == int(meta["seed"])

        episode_return = 0.0
        for i, (step, color, depth, (action, reward, terminated, truncated, obs)) in enumerate(
            zip(steps, colors, depths, run)
        ):
            assert step.step == i
            assert step.action_discrete == (-1 if action is None else int(action))
            assert step.reward == reward
            assert (bool(step.terminated), bool(step.truncated)) == (terminated, truncated)
            episode_return += reward
            assert step.episode_return == episode_return
            # The observation's colour is the recorded frame (rendered at
            # the observation's size), byte for byte.
            assert (color.encoding, color.height, color.width) == ("rgb8", H, W)
            image = np.frombuffer(color.data, np.uint8).reshape(H, W, 3)
            np.testing.assert_array_equal(image, obs[..., :3])
            assert (depth.encoding, depth.height, depth.width) == ("32FC1", H, W)
            metres = np.frombuffer(depth.data, "<f4").reshape(H, W)
            # Depth in the observation is 0 where the camera saw nothing.
            np.testing.assert_array_equal(obs[..., 3] == 0, ~np.isfinite(metres) | (metres <= 0))
            stamp = step.header.stamp.sec * 10**9 + step.header.stamp.nanosec
            assert stamp == color.header.stamp.sec * 10**9 + color.header.stamp.nanosec
        stamps = [t for t, _ in by_topic["/offworld/step"]]
        assert stamps == sorted(stamps), "steps logged at their capture times, in order"
        [(_, end)] = by_topic["/offworld/episode_end"]
        assert end.steps == len(run) - 1
        assert end.episode_return == episode_return
        assert end.end_reason != ""


def test_schemas_are_ros2_jazzys_and_our_types_register(tmp_path: Path):
    _record(tmp_path, "OffWorldMonolithContinuousSim-v0", episodes=1, steps=2)
    [path] = _files(tmp_path)
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(path) as bag:
        for conn in bag.connections:
            types = get_types_from_msg(conn.msgdef.data, conn.msgtype)
            if conn.msgtype in STANDARD:
                # Same fields as ROS 2 itself, so the same RIHS01 hash.
                for name, fields in types.items():
                    assert fields == jazzy.fielddefs[name], name
            else:
                assert conn.msgtype.startswith("offworld_msgs/msg/")
                store.register(types)
        for name in STANDARD:
            assert store.hash_rihs01(name) == jazzy.hash_rihs01(name)
        steps = [store.deserialize_cdr(raw, c.msgtype) for c, _, raw in bag.messages() if c.topic == "/offworld/step"]
    assert len(steps) == 3
    assert [len(s.action_continuous) for s in steps] == [0, 2, 2]
    assert all(-1 <= v <= 1 for s in steps[1:] for v in s.action_continuous)


def test_record_is_refused_for_remote_envs():
    with pytest.raises(ConfigurationError, match="env_controller serve --record"):
        gymnasium.make("OffWorldMonolithDiscreteSim-v0", connect="tcp/127.0.0.1:1", record="runs")


def _decode_all(path: Path) -> dict[str, int]:
    """Messages per topic, every one decoded by both readers."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        mcap_count = sum(1 for _ in reader.iter_decoded_messages())
    counts: dict[str, int] = {}
    with AnyReader([path]) as bag:
        for conn, _, raw in bag.messages():
            bag.deserialize(raw, conn.msgtype)
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
    assert sum(counts.values()) == mcap_count
    return counts


def test_kill_9_leaves_every_completed_episode_readable_and_the_cut_one_recoverable(tmp_path: Path):
    env_id = "sim/recorded-0"
    runs = tmp_path / "runs"
    proc, endpoint = start_controller(tmp_path, env_id, "--record", str(runs))
    try:
        env = gymnasium.make(
            "OffWorldMonolithDiscreteSim-v0", connect=endpoint, env_id=env_id, resolution=(24, 32)
        )
        steps_taken = []
        for episode in range(3):
            env.reset(seed=episode)
            steps = 0
            for action in (0, 1, 2):
                _, _, terminated, truncated, _ = env.step(action)
                steps += 1
                if terminated or truncated:
                    break
            steps_taken.append(steps)
        # Episode 2 is running: the controller dies without a word.
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        stop(proc)
    files = sorted(runs.rglob("ep-*"))
    assert [f.name for f in files] == ["ep-000000.mcap", "ep-000001.mcap", "ep-000002.mcap.partial"]
    # Complete episodes open in both readers; a reset ended each of them.
    for path, steps in zip(files[:2], steps_taken):
        counts = _decode_all(path)
        assert counts["/offworld/step"] == steps + 1
        assert counts["/offworld/episode_end"] == 1
    # The cut one streams up to its last complete chunk, then ends: at the
    # file's end or at the chunk being written (its length still unset).
    partial = files[2]
    channels: dict[int, str] = {}
    streamed: dict[str, int] = {}
    with open(partial, "rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False).records:
                if isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message):
                    topic = channels[record.channel_id]
                    streamed[topic] = streamed.get(topic, 0) + 1
                elif isinstance(record, Footer):
                    pytest.fail("a .partial has no footer")
        except (EndOfFile, RecordLengthLimitExceeded):
            pass
    assert streamed["/offworld/episode"] == 1
    # …rosbags refuses it as it is, and `recorder recover` makes it whole.
    with pytest.raises(Exception):
        with AnyReader([partial]) as bag:
            list(bag.messages())
    subprocess.run([str(_binary("recorder")), "recover", str(partial)], check=True, capture_output=True)
    recovered = partial.with_name("ep-000002.mcap")
    counts = _decode_all(recovered)
    assert counts == streamed, "recover keeps exactly what the partial file held"
    # Sim files are flushed per ~1 MiB chunk (320×240 frames: every other
    # step or so) and the writer may lag the kill: some steps, maybe none.
    assert counts.get("/offworld/step", 0) <= steps_taken[2] + 1
    assert "/offworld/episode_end" not in counts, "the episode's end was never recorded"
    assert counts["/offworld/episode"] == 1


def test_recorder_info_lists_the_episodes(tmp_path: Path):
    _record(tmp_path, "OffWorldMonolithDiscreteSim-v0", episodes=2, steps=3)
    out = subprocess.run(
        [str(_binary("recorder")), "info", str(tmp_path)],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.splitlines()
    assert len(out) == 2
    assert "episode 0: " in out[0] and "episode 1: " in out[1]
    assert all("/offworld/step=" in line for line in out)
