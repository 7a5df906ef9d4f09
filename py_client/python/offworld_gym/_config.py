"""Resolves constructor keywords into the native layer's arguments."""

from __future__ import annotations

import numbers
import os
from dataclasses import dataclass
from typing import Any, Sequence

import gymnasium
import numpy as np

from offworld_gym.envs.common.channels import Channels
from offworld_gym.envs.common.enums import AlgorithmMode, LearningType
from offworld_gym.errors import ConfigurationError

#: Environment variables users of the original service know.
TOKEN_ENV = "OFFWORLD_GYM_ACCESS_TOKEN"
CONNECT_ENV = "OFFWORLD_GYM_CONNECT"
ENV_ID_ENV = "OFFWORLD_GYM_ENV"
#: ``env_id=DISCOVER``: use any free envs of the task the deployment lists
#: (on any host behind its router).
DISCOVER = "discover"
#: Turns the rerun monitor on without touching code (same values as ``rerun=``).
RERUN_ENV = "OFFWORLD_GYM_RERUN"
#: Records embedded envs' episodes without touching code (same as ``record=``).
RECORD_ENV = "OFFWORLD_GYM_RECORD"
#: The longest ``wait=`` (a year; the client's ``LONGEST_WAIT``).
LONGEST_WAIT_S = 365 * 86_400


@dataclass(frozen=True)
class NativeOptions:
    """What ``NativeEnvs(options)`` reads, by attribute name (its Rust
    side: ``OpenOptions`` in ``py_client/src/lib.rs``)."""

    task: str
    realm: str
    num_envs: int
    connect: str | None
    env_ids: list[str] | None
    token: str
    experiment_name: str
    resume_experiment: bool
    learning_type: str
    algorithm_mode: str
    channels: Channels
    height: int
    width: int
    depth_format: str
    rerun: str | None
    record: str | None
    twin_profile: str | None
    wait_s: float


@dataclass
class Resolved:
    """Everything the native constructor needs, plus what Python keeps."""

    native: NativeOptions
    channels: Channels
    render_extra_rgb: bool
    height: int
    width: int
    float_obs: bool


def resolve(
    task: str,
    realm: str,
    num_envs: int,
    *,
    channel_type: Channels | int = Channels.DEPTH_ONLY,
    resolution: Sequence[int] = (240, 320),
    depth_format: str = "uint8",
    experiment_name: str = "",
    resume_experiment: bool = False,
    learning_type: LearningType | str = LearningType.END_TO_END,
    algorithm_mode: AlgorithmMode | str = AlgorithmMode.TRAIN,
    connect: str | None = None,
    env_id: str | Sequence[str] | None = None,
    token: str | None = None,
    render_mode: str | None = None,
    rerun: str | os.PathLike[str] | None = None,
    record: str | os.PathLike[str] | None = None,
    twin_profile: str | os.PathLike[str] | None = None,
    wait: float | None = None,
) -> Resolved:
    """Checks and resolves keyword arguments (environment variables fill gaps).

    ``rerun``: stream the envs to the rerun viewer while they run — a
    ``.rrd`` path (complete after ``close()``), a viewer URL such as
    ``rerun+http://127.0.0.1:9876/proxy``, or ``serve``/``serve:<ip>:<port>``
    to host a server viewers connect to. The demo's lean build has no
    monitor and refuses it (``BadRequest``, saying how to get the full one).

    ``record``: a directory where every episode of the embedded envs is
    recorded as an MCAP file (``docs/recording.md``); a deployment's
    controller records its envs itself (``env_controller serve --record``).

    ``twin_profile``: a twin profile file (``docs/twin-profile.md``) the
    embedded sim twins are built with, so they behave like one physical
    robot; a bad file raises ``BadRequest`` naming the file and the field.

    ``wait``: seconds to wait in line when an env is leased by someone
    else, instead of raising ``Busy`` at once (each refusal says the place
    in line, on stderr); first come, first served. A booked slot's holder
    still goes first.
    """
    channels = Channels(channel_type)
    wait_s = 0.0 if wait is None else wait
    if isinstance(wait_s, bool) or not isinstance(wait_s, numbers.Real) or not 0 <= wait_s <= LONGEST_WAIT_S:
        raise ConfigurationError(f"wait must be a number of seconds from 0 to {LONGEST_WAIT_S} (a year), got {wait!r}")
    if len(resolution) != 2:
        raise ConfigurationError(f"resolution must be (height, width), got {resolution!r}")
    # A whole number of pixels, not silently truncated: (84.5, 84) is a mistake.
    if not all(isinstance(v, numbers.Integral) and not isinstance(v, bool) for v in resolution):
        raise ConfigurationError(
            f"resolution (height, width) = {tuple(resolution)!r}: each side must be a whole number of pixels"
        )
    height, width = (int(v) for v in resolution)
    if depth_format not in ("uint8", "meters"):
        raise ConfigurationError(f'depth_format must be "uint8" or "meters", got {depth_format!r}')
    if render_mode not in (None, "rgb_array"):
        raise ConfigurationError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
    rerun = os.fspath(rerun) if rerun is not None else os.environ.get(RERUN_ENV) or None
    record = os.fspath(record) if record is not None else os.environ.get(RECORD_ENV) or None
    connect = connect or os.environ.get(CONNECT_ENV)
    token = token if token is not None else os.environ.get(TOKEN_ENV, "")
    remote = connect is not None or "OFFWORLD_ZENOH_CONFIG" in os.environ or "OFFWORLD_ZENOH_CONNECT" in os.environ
    if realm == "real":
        if not remote:
            raise ConfigurationError(
                "real envs need a deployment: pass connect='tcp/host:7447' or set OFFWORLD_GYM_CONNECT"
            )
        if not token:
            raise ConfigurationError(f"real envs need an access token: pass token=… or set {TOKEN_ENV}")
    if record is not None and (remote or realm != "sim"):
        raise ConfigurationError(
            "record= records embedded sim envs; a deployment records on its controller "
            "(env_controller serve --record DIR)"
        )
    if twin_profile is not None and (remote or realm != "sim"):
        raise ConfigurationError(
            "twin_profile= shapes embedded sim twins; a deployment's twins take `sim_twin --profile FILE`"
        )
    env_ids = None
    if remote:
        world = "monolith_obstacle" if task.startswith("MonolithObstacle") else "monolith"
        chosen = env_id or os.environ.get(ENV_ID_ENV) or f"{realm}/{world}-0"
        if chosen == DISCOVER:
            env_ids = None  # the native layer picks free envs of the task
        else:
            env_ids = [chosen] if isinstance(chosen, str) else list(chosen)
            if len(env_ids) == 1 and num_envs > 1:
                base = env_ids[0]
                env_ids = [f"{base}-{i}" for i in range(num_envs)]
            if len(env_ids) != num_envs:
                raise ConfigurationError(f"{num_envs} envs need {num_envs} env ids, got {env_ids}")
    # Rendering needs colour: fetch RGBD and keep the requested channels.
    render_extra_rgb = render_mode == "rgb_array" and channels == Channels.DEPTH_ONLY
    wire_channels = Channels.RGBD if render_extra_rgb else channels
    return Resolved(
        native=NativeOptions(
            task=task,
            realm=realm,
            num_envs=num_envs,
            connect=connect,
            env_ids=env_ids,
            token=token,
            experiment_name=experiment_name,
            resume_experiment=bool(resume_experiment),
            learning_type=LearningType(learning_type).value,
            algorithm_mode=AlgorithmMode(algorithm_mode).value,
            channels=wire_channels,
            height=height,
            width=width,
            depth_format=depth_format,
            rerun=rerun,
            record=record,
            twin_profile=os.fspath(twin_profile) if twin_profile is not None else None,
            wait_s=float(wait_s),
        ),
        channels=channels,
        render_extra_rgb=render_extra_rgb,
        height=height,
        width=width,
        float_obs=depth_format == "meters",
    )


def observation_space(r: Resolved) -> gymnasium.spaces.Box:
    """Box (height, width, channels): uint8 0–255, or float32 (RGB 0–255, depth in m)."""
    shape = (r.height, r.width, r.channels.count)
    if r.float_obs:
        return gymnasium.spaces.Box(low=0.0, high=255.0, shape=shape, dtype=np.float32)
    return gymnasium.spaces.Box(low=0, high=255, shape=shape, dtype=np.uint8)


def action_space(spec: dict[str, Any]) -> gymnasium.spaces.Space:
    """Discrete(n) or Box([-1, 1]^2, float32) from the server's spec."""
    if spec["action_kind"] == "discrete":
        return gymnasium.spaces.Discrete(int(spec["action_n"]))
    low = np.asarray(spec["action_low"], dtype=np.float32)
    high = np.asarray(spec["action_high"], dtype=np.float32)
    return gymnasium.spaces.Box(low=low, high=high, dtype=np.float32)


def split(r: Resolved, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(observation as requested, RGB image for rendering or None). The
    image is uint8 as gymnasium's ``rgb_array`` wants, also when the
    observation is float32 (``depth_format="meters"`` keeps colour in 0..255)."""
    if r.render_extra_rgb or r.channels in (Channels.RGB_ONLY, Channels.RGBD):
        return requested(r, obs), _rgb8(obs[..., :3])
    return obs, None


def requested(r: Resolved, obs: np.ndarray) -> np.ndarray:
    """The observation as requested: without the colour fetched only for rendering."""
    return obs[..., 3:] if r.render_extra_rgb else obs


def _rgb8(rgb: np.ndarray) -> np.ndarray:
    return rgb if rgb.dtype == np.uint8 else rgb.astype(np.uint8)
