"""offworld_gym against real Zenoh sessions: the embedded sim by default, a
separate deployment process where a test needs one."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap
import time

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import offworld_gym
from conftest import _free_port
from offworld_gym import errors
from offworld_gym.envs.common.channels import Channels
from offworld_gym.envs.common.enums import AlgorithmMode, LearningType

SIM_IDS = [i for i, (_, realm) in offworld_gym.ENV_IDS.items() if realm == "sim"]
REAL_IDS = [i for i, (_, realm) in offworld_gym.ENV_IDS.items() if realm == "real"]
LEGACY_SIM_IDS = [i for i, (_, realm) in offworld_gym.LEGACY_IDS.items() if realm == "sim"]


def test_all_ids_are_registered():
    assert len(offworld_gym.ENV_IDS) == 8
    for env_id in [*offworld_gym.ENV_IDS, *offworld_gym.LEGACY_IDS]:
        assert env_id in gymnasium.registry, env_id


def test_the_papers_listing_runs_as_written(monkeypatch):
    for var in ("OFFWORLD_GYM_CONNECT", "OFFWORLD_GYM_ACCESS_TOKEN", "OFFWORLD_ZENOH_CONFIG", "OFFWORLD_ZENOH_CONNECT"):
        monkeypatch.delenv(var, raising=False)
    # Real without a deployment: a clear error naming what is missing.
    with pytest.raises(errors.ConfigurationError, match="connect"):
        gymnasium.make(
            "OffWorldMonolithDiscreteReal-v0",
            experiment_name="Demo",
            resume_experiment=False,
            channel_type=Channels.DEPTH_ONLY,
        )
    with pytest.raises(errors.ConfigurationError, match="token"):
        gymnasium.make("OffWorldMonolithDiscreteReal-v0", connect="tcp/127.0.0.1:9", experiment_name="Demo")
    # The same listing on the sim id trains at once.
    env = gymnasium.make(
        "OffWorldMonolithDiscreteSim-v0",
        experiment_name="Demo",
        resume_experiment=False,
        channel_type=Channels.DEPTH_ONLY,
        learning_type=LearningType.END_TO_END,
        algorithm_mode=AlgorithmMode.TRAIN,
    )
    obs, info = env.reset()
    assert obs.shape == (240, 320, 1) and obs.dtype == np.uint8
    assert set(info) == {"step", "is_success", "end_reason", "pose", "distance_to_goal"}
    assert (info["step"], info["is_success"], info["end_reason"]) == (0, False, "")
    assert env.unwrapped.episode_id == 0
    # Sim envs share the ground truth: the pose and its distance to the monolith.
    x, y, yaw = info["pose"]
    assert info["distance_to_goal"] == pytest.approx(math.hypot(x - 0.0109, y + 0.2034))
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert isinstance(reward, float) and isinstance(terminated, bool) and isinstance(truncated, bool)
    assert info["step"] == 1
    assert len(info["pose"]) == 3 and info["distance_to_goal"] >= 0
    env.close()


@pytest.mark.parametrize("env_id", SIM_IDS + LEGACY_SIM_IDS)
def test_every_sim_id_passes_gymnasium_check_env(env_id):
    env = gymnasium.make(env_id, resolution=(84, 84), render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=False)
    env.close()


@pytest.mark.parametrize("env_id", REAL_IDS)
def test_real_ids_without_deployment_fail_clearly(env_id, monkeypatch):
    monkeypatch.delenv("OFFWORLD_GYM_CONNECT", raising=False)
    with pytest.raises(errors.ConfigurationError):
        gymnasium.make(env_id)


def test_an_unreachable_endpoint_is_an_error_naming_it_not_an_empty_deployment(monkeypatch):
    """Nothing listens there: listing, opening an env and the CLI all say so
    within seconds, naming the endpoint (and the CLI exits non-zero)."""
    monkeypatch.delenv("OFFWORLD_GYM_CONNECT", raising=False)
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    started = time.monotonic()
    with pytest.raises(errors.Unavailable, match=f"nothing answered at {endpoint}"):
        offworld_gym.list_envs(connect=endpoint)
    with pytest.raises(errors.Unavailable, match=f"nothing answered at {endpoint}"):
        gymnasium.make("OffWorldMonolithDiscreteSim-v0", connect=endpoint)
    cli = subprocess.run(
        [sys.executable, "-m", "offworld_gym", "envs", "--connect", endpoint],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert cli.returncode == 1, cli
    assert f"nothing answered at {endpoint}" in cli.stderr, cli.stderr
    # Bounded (each waits a few seconds for the endpoint), not a hang.
    assert time.monotonic() - started < 45


def test_stable_baselines3_check_env_when_installed():
    sb3 = pytest.importorskip("stable_baselines3.common.env_checker")
    for env_id in SIM_IDS:
        env = gymnasium.make(env_id, resolution=(84, 84))
        sb3.check_env(env.unwrapped)
        env.close()


def test_info_says_how_each_episode_ended():
    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", resolution=(24, 32))
    env.action_space.seed(5)
    ends = []
    try:
        for episode in range(3):
            env.reset(seed=episode)
            while True:
                _, reward, terminated, truncated, info = env.step(env.action_space.sample())
                assert env.unwrapped.episode_id == episode
                if not (terminated or truncated):
                    assert (info["is_success"], info["end_reason"]) == (False, "")
                    continue
                assert info["is_success"] == (reward > 0)
                expected = "success" if reward > 0 else ("out_of_bounds" if terminated else "step_limit")
                assert info["end_reason"] == expected
                if info["is_success"]:
                    assert info["distance_to_goal"] <= 0.40  # the world's success_radius
                ends.append(info["end_reason"])
                break
    finally:
        env.close()
    assert len(ends) == 3


def test_seeded_resets_are_deterministic():
    def run(env, seed):
        obs, _ = env.reset(seed=seed)
        frames = [obs]
        for a in [2, 0, 2, 1, 3]:
            obs, *_ = env.step(a)
            frames.append(obs)
        return frames

    env = gymnasium.make("OffWorldMonolithObstacleDiscreteSim-v0", resolution=(84, 84), channel_type=Channels.RGBD)
    a, b = run(env, 11), run(env, 11)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(run(env, 12)[0], a[0])
    env.close()


def test_observation_options():
    env = gymnasium.make(
        "OffWorldMonolithContinuousSim-v0", resolution=(60, 80), channel_type=Channels.RGBD, depth_format="meters"
    )
    obs, _ = env.reset(seed=1)
    assert obs.shape == (60, 80, 4) and obs.dtype == np.float32
    assert env.observation_space.contains(obs)
    depth = obs[..., 3]
    assert 0.0 < np.median(depth[depth > 0]) < 10.0, "metric depth"
    assert env.action_space == gymnasium.spaces.Box(-1.0, 1.0, (2,), np.float32)
    env.close()
    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", resolution=(84, 84), channel_type=Channels.RGB_ONLY)
    obs, _ = env.reset(seed=1)
    assert obs.shape == (84, 84, 3) and obs.dtype == np.uint8
    env.close()


@pytest.mark.parametrize("depth_format", ["uint8", "meters"])
def test_observations_are_writable_arrays_of_their_own_whose_memory_serves_later_steps(depth_format):
    """A step allocates no new 307 KB array (and its page faults) while the
    last one was dropped, and never touches an array still held."""
    env = gymnasium.make(
        "OffWorldMonolithDiscreteSim-v0",
        resolution=(84, 84),
        channel_type=Channels.DEPTH_ONLY,
        depth_format=depth_format,
    )
    env.reset(seed=3)
    env.step(2)  # gymnasium's checker holds on to the first step's result
    held, *_ = env.step(2)
    assert held.flags.writeable and held.flags.c_contiguous
    held[...] = 7
    second, *_ = env.step(2)
    assert (held == 7).all(), "a later step leaves a held array alone"
    assert not (second == 7).all()
    address = second.__array_interface__["data"][0]
    expected = second.copy()
    del second
    third, *_ = env.step(2)
    assert third.__array_interface__["data"][0] == address, "the dropped array's memory again"
    assert not np.array_equal(third, expected), "holding the new observation"
    env.close()


def test_render_threads_come_from_the_environment_and_change_no_pixel(monkeypatch):
    """OFFWORLD_RENDER_THREADS sets the threads the embedded twin renders
    each frame on: a seed's observations are the same bytes on 1 and 3; a
    value that is not a thread count is refused, naming the variable."""

    def walk(threads):
        monkeypatch.setenv("OFFWORLD_RENDER_THREADS", threads)
        env = gymnasium.make("OffWorldMonolithObstacleDiscreteSim-v0", channel_type=Channels.RGBD)
        obs, _ = env.reset(seed=5)
        frames = [obs]
        for action in [0, 2, 2, 1, 2]:
            frames.append(env.step(action)[0])
        env.close()
        return [f.tobytes() for f in frames]

    one, three = walk("1"), walk("3")
    assert one[0] != one[-1], "the robot moved: the frames differ"
    assert one == three
    for bad in ["0", "many", "65"]:
        monkeypatch.setenv("OFFWORLD_RENDER_THREADS", bad)
        with pytest.raises(errors.BadRequest, match="OFFWORLD_RENDER_THREADS"):
            gymnasium.make("OffWorldMonolithDiscreteSim-v0")


def test_twin_stepping_comes_from_the_environment_and_changes_no_observation(monkeypatch):
    """One embedded env simulates on the caller's thread unless
    OFFWORLD_TWIN_STEPPING=own-thread gives its twin a thread: a seed's
    observations, rewards and ends are the same either way; a value that is
    not a stepping is refused, naming the variable."""

    def walk(stepping):
        monkeypatch.setenv("OFFWORLD_TWIN_STEPPING", stepping)
        env = gymnasium.make("OffWorldMonolithObstacleDiscreteSim-v0", channel_type=Channels.RGBD)
        obs, _ = env.reset(seed=5)
        steps = [(obs.tobytes(), 0.0, False, False)]
        for action in [0, 2, 2, 1, 2]:
            obs, reward, terminated, truncated, _ = env.step(action)
            steps.append((obs.tobytes(), reward, terminated, truncated))
        env.close()
        return steps

    default, own, arrival = walk(""), walk("own-thread"), walk("on-arrival")
    assert default[0][0] != default[-1][0], "the robot moved: the frames differ"
    assert default == own == arrival
    for bad in ["thread", "ON-ARRIVAL", "1"]:
        monkeypatch.setenv("OFFWORLD_TWIN_STEPPING", bad)
        with pytest.raises(errors.BadRequest, match="OFFWORLD_TWIN_STEPPING"):
            gymnasium.make("OffWorldMonolithDiscreteSim-v0")


def test_bad_actions_raise_typed_errors():
    env = gymnasium.make("OffWorldMonolithContinuousSim-v0", resolution=(32, 32))
    with pytest.raises(errors.InvalidState):
        # Below gymnasium's order-enforcing wrapper: the server refuses too.
        env.unwrapped.step(np.zeros(2, dtype=np.float32))
    env.reset(seed=0)
    for bad in ([1.5, 0.0], [np.nan, 0.0], [0.0], [0.0, 0.0, 0.0]):
        with pytest.raises(errors.BadRequest) as info:
            env.step(np.array(bad, dtype=np.float32))
        assert info.value.code == 400
        # One hierarchy: catching the package's base (or the builtin) works.
        assert isinstance(info.value, errors.OffWorldGymError) and isinstance(info.value, ValueError)
    with pytest.raises(ValueError):
        env.step("left")
    obs, *_ = env.step(np.array([0.5, -0.5], dtype=np.float32))
    assert obs.shape == (32, 32, 1), "still serving after bad actions"
    env.close()
    env.close()
    discrete = gymnasium.make("OffWorldMonolithDiscreteSim-v0", resolution=(32, 32))
    discrete.reset(seed=0)
    with pytest.raises(errors.BadRequest):
        discrete.step(4)
    discrete.step(np.int64(2))
    discrete.close()


def test_every_error_class_is_an_offworld_gym_error_and_its_builtin():
    expected = {
        errors.BadRequest: (400, ValueError),
        errors.Unauthorized: (401, PermissionError),
        errors.NotFound: (404, LookupError),
        errors.Busy: (409, None),
        errors.InvalidState: (412, None),
        errors.Internal: (500, None),
        errors.Unavailable: (503, ConnectionError),
        errors.Timeout: (504, TimeoutError),
    }
    for cls, (code, builtin) in expected.items():
        assert issubclass(cls, errors.OffWorldGymError), cls
        assert cls.code == code
        if builtin is not None:
            assert issubclass(cls, builtin), cls
    assert issubclass(errors.ConfigurationError, errors.OffWorldGymError)
    assert issubclass(errors.ConfigurationError, ValueError)


def test_render_returns_rgb():
    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", resolution=(48, 64), render_mode="rgb_array")
    obs, _ = env.reset(seed=2)
    assert obs.shape == (48, 64, 1)
    frame = env.render()
    assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8 and frame.max() > 0
    env.close()
    # Metres: the observation is float32, the rendered image still uint8,
    # the same pixels as the observation's colour channels.
    metres = gymnasium.make(
        "OffWorldMonolithDiscreteSim-v0",
        resolution=(24, 32),
        render_mode="rgb_array",
        depth_format="meters",
        channel_type=Channels.RGBD,
    )
    obs, _ = metres.reset(seed=2)
    frame = metres.render()
    assert obs.dtype == np.float32 and frame.dtype == np.uint8
    assert np.array_equal(frame, obs[..., :3].astype(np.uint8))
    metres.close()


@pytest.mark.parametrize("resolution", [(-1, 84), (0, 84), (84, 2**40), (4800, 6400)])
def test_a_resolution_out_of_range_is_named_with_the_accepted_range(resolution):
    with pytest.raises(errors.BadRequest, match=r"resolution \(height, width\) = .*each side must be 1\.\.=1024") as info:
        gymnasium.make("OffWorldMonolithDiscreteSim-v0", resolution=resolution)
    assert f"({resolution[0]}, {resolution[1]})" in str(info.value)
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize("resolution", [(84.5, 84), (84, "84"), (True, 84)])
def test_a_resolution_that_is_not_whole_pixels_is_refused_not_truncated(resolution):
    with pytest.raises(errors.ConfigurationError, match="each side must be a whole number of pixels") as info:
        gymnasium.make("OffWorldMonolithDiscreteSim-v0", resolution=resolution)
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize("wait", [-1, float("nan"), float("inf"), 10**400, "60", True])
def test_a_wait_that_is_not_seconds_is_refused(wait):
    with pytest.raises(errors.ConfigurationError, match=r"wait must be a number of seconds from 0 to 31536000 \(a year\), got") as info:
        gymnasium.make("OffWorldMonolithDiscreteSim-v0", resolution=(12, 16), wait=wait)
    assert isinstance(info.value, ValueError)


def test_numpy_integers_are_whole_pixels():
    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", resolution=(np.int64(12), np.int32(16)))
    obs, _ = env.reset(seed=1)
    assert obs.shape[:2] == (12, 16)
    env.close()


def test_vector_env_shapes_and_autoreset():
    envs = gymnasium.make_vec("OffWorldMonolithDiscreteSim-v0", num_envs=2, resolution=(32, 32))
    assert type(envs).__name__ == "OffWorldMonolithVectorEnv", "the native vector entry point is used"
    obs, info = envs.reset(seed=5)
    assert obs.shape == (2, 32, 32, 1)
    assert list(info["step"]) == [0, 0]
    done_seen = False
    for _ in range(100):
        obs, rewards, terminated, truncated, info = envs.step(np.array([2, 2]))
        assert obs.shape == (2, 32, 32, 1) and rewards.shape == (2,)
        if (terminated | truncated).any():
            done_seen = True
            ended = terminated | truncated
            obs, rewards, terminated, truncated, info = envs.step(np.array([2, 2]))
            # Next-step autoreset: the finished env restarts at step 0, reward 0.
            assert (info["step"][ended] == 0).all()
            assert (rewards[ended] == 0).all()
            break
    assert done_seen, "FORWARD for 100 steps ends an episode"
    envs.close()


@pytest.mark.parametrize("depth_format", ["uint8", "meters"])
def test_vector_observations_are_one_batch_a_later_step_leaves_alone(depth_format):
    envs = gymnasium.make_vec(
        "OffWorldMonolithDiscreteSim-v0",
        num_envs=2,
        resolution=(24, 32),
        channel_type=Channels.RGBD,
        depth_format=depth_format,
    )
    first, _ = envs.reset(seed=5)
    dtype = np.uint8 if depth_format == "uint8" else np.float32
    assert first.shape == (2, 24, 32, 4) and first.dtype == dtype and first.flags.c_contiguous
    kept = first.copy()
    second, *_ = envs.step(np.array([2, 2]))
    assert np.array_equal(first, kept), "a held batch is not reused"
    assert not np.array_equal(second, first), "the envs moved"
    # The same seeds give the same batch as two single envs.
    for i in range(2):
        env = gymnasium.make(
            "OffWorldMonolithDiscreteSim-v0", resolution=(24, 32), channel_type=Channels.RGBD, depth_format=depth_format
        )
        alone, _ = env.reset(seed=5 + i)
        assert np.array_equal(alone, first[i])
        env.close()
    envs.close()


def test_a_vector_env_rendering_a_depth_observation_returns_depth_alone():
    envs = gymnasium.make_vec(
        "OffWorldMonolithDiscreteSim-v0", num_envs=2, resolution=(24, 32), render_mode="rgb_array"
    )
    obs, _ = envs.reset(seed=5)
    assert obs.shape == (2, 24, 32, 1) and obs.flags.c_contiguous
    envs.close()


def test_second_process_gets_busy(deployment):
    endpoint, env_id = deployment
    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", connect=endpoint, env_id=env_id, resolution=(32, 32))
    env.reset(seed=0)
    contender = textwrap.dedent(
        f"""
        import gymnasium, offworld_gym
        from offworld_gym import errors
        try:
            gymnasium.make("OffWorldMonolithDiscreteSim-v0", connect="{endpoint}", env_id="{env_id}", token="")
        except errors.Busy as e:
            print("BUSY", e.code, e)
        """
    )
    out = subprocess.run([sys.executable, "-c", contender], capture_output=True, text=True, timeout=60)
    assert "BUSY 409" in out.stdout, out.stdout + out.stderr
    assert "until" in out.stdout
    env.close()
    # Released: the other process may now take it.
    again = gymnasium.make("OffWorldMonolithDiscreteSim-v0", connect=endpoint, env_id=env_id, resolution=(32, 32))
    again.close()
