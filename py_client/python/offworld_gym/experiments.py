"""Experiments, their episodes and recordings, and the leaderboard: the
records the controller keeps of every episode, as ``env_controller
experiments`` and ``env_controller leaderboard`` print them on the
controller's host.

You see your own experiments (operators: everyone's); another user's
experiment is reported as not found. The leaderboard is public. For the env
you are training on, ``env.unwrapped.experiment()`` and
``env.unwrapped.episodes()`` ask the deployment that env runs on (embedded
ones included)."""

from __future__ import annotations

import os
from typing import TypedDict

from offworld_gym import _native
from offworld_gym._config import CONNECT_ENV, TOKEN_ENV


class Experiment(TypedDict):
    """One experiment: a named series of episodes by one user on one env."""

    id: int
    #: Owner's user name (``anonymous`` for sim envs opened without a token).
    user: str
    env_id: str
    #: ``MonolithDiscrete`` etc.
    task: str
    name: str
    #: ``end2end``, ``sim2real`` or ``humandemos`` (see ``LearningType``).
    learning_type: str
    #: ``train`` or ``test`` (see ``AlgorithmMode``).
    algorithm_mode: str
    #: Episodes started (the one in progress included).
    episodes: int
    #: Steps taken in them.
    steps: int
    created_unix_ms: int
    #: Last used.
    updated_unix_ms: int


class Recording(TypedDict):
    """One MCAP file of an episode."""

    #: Relative to the controller's recording directory (``serve --record``
    #: or ``record=``), ``/``-separated:
    #: ``sim/monolith-0/exp-000001/ep-000000.mcap``.
    path: str
    bytes: int
    #: False for a ``.partial`` file, cut short by a crash
    #: (``recorder recover`` finishes it).
    complete: bool


class ResetAccuracy(TypedDict):
    """How well a reset put the robot at its spawn pose."""

    #: The spawn pose asked for: ``(x m, y m, yaw rad)``, world frame.
    requested: tuple[float, float, float]
    #: The pose the episode started from.
    achieved: tuple[float, float, float]
    position_error_m: float
    #: Absolute, wrapped to ``[0, pi]``.
    yaw_error_rad: float
    #: From the reset request to its first observation.
    duration_s: float
    #: When the reset ended.
    unix_ms: int


class Episode(TypedDict):
    """One episode of an experiment."""

    #: Index within the experiment (``env.unwrapped.episode_id``).
    index: int
    #: The seed its reset was given, if any.
    seed: int | None
    steps: int
    #: Sum of its rewards.
    episode_return: float
    #: Reached the monolith.
    success: bool
    #: ``success``, ``out_of_bounds``, ``step_limit``, ``in_progress`` or
    #: why it was cut short (``aborted: …``, ``closed``, …).
    end_reason: str
    started_unix_ms: int
    #: Equal to the start while in progress.
    ended_unix_ms: int
    #: How well its reset put the robot at its spawn pose (None for episodes
    #: stored before resets were timed).
    reset: ResetAccuracy | None
    #: Its files, when the env records (none otherwise).
    recordings: list[Recording]


class LeaderboardEntry(TypedDict):
    """One test-mode experiment, ranked by success rate, then mean return."""

    #: From 1.
    rank: int
    experiment: str
    user: str
    learning_type: str
    #: Episodes evaluated (aborted ones do not count).
    episodes: int
    #: In [0, 1].
    success_rate: float
    mean_return: float


def _token(token: str | None) -> str:
    """The token given, else ``OFFWORLD_GYM_ACCESS_TOKEN``, else anonymous
    (which sim deployments admit)."""
    return token if token is not None else os.environ.get(TOKEN_ENV, "")


def experiments(env_id: str, *, token: str | None = None, connect: str | None = None) -> list[Experiment]:
    """Your experiments on ``env_id`` (operators: everyone's), most recently
    used first. Raises ``Unauthorized`` for an unknown token."""
    return _native.experiments(env_id, _token(token), connect or os.environ.get(CONNECT_ENV))  # type: ignore[return-value]


def experiment(
    env_id: str, experiment_id: int, *, token: str | None = None, connect: str | None = None
) -> tuple[Experiment, list[Episode]]:
    """One of your experiments on ``env_id`` and all its episodes, in order,
    with their returns, lengths and recordings. Raises ``NotFound`` if it is
    not yours or does not exist."""
    found, episodes = _native.experiment_episodes(
        env_id, experiment_id, _token(token), connect or os.environ.get(CONNECT_ENV)
    )
    return found, episodes  # type: ignore[return-value]


def leaderboard(env_id: str, *, connect: str | None = None) -> list[LeaderboardEntry]:
    """The test-mode experiments of ``env_id``, best first."""
    return _native.leaderboard(env_id, connect or os.environ.get(CONNECT_ENV))  # type: ignore[return-value]
