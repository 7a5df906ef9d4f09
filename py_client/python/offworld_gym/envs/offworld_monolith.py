"""The Monolith task as a gymnasium environment (all eight ids)."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

from offworld_gym import _config
from offworld_gym._native import NativeEnvs
from offworld_gym.experiments import Episode, Experiment


class OffWorldMonolithEnv(gymnasium.Env):
    """A ROSbot must reach the monolith from camera input only.

    Observations are ``(height, width, channels)`` arrays; rewards +1 on
    reaching the monolith, else 0; episodes end on success, on leaving the
    boundary (terminated) or after 100 steps (truncated).

    Ctrl-C during any call that waits (creating the env, ``reset``,
    ``step``, ``close``) raises ``KeyboardInterrupt`` within ~0.1 s. The env
    stays open and usable: the interrupted request has already reached the
    controller, which completes it, and the next call waits for that, then
    runs. Call ``reset()`` before stepping again (the interrupted call's
    observation is lost; stepping an episode it ended raises
    ``errors.InvalidState``). An interrupted ``close()`` still releases the
    lease: the env counts as closed.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}

    def __init__(
        self,
        task: str,
        realm: str,
        random_init: bool = True,
        render_mode: str | None = None,
        **options: Any,
    ) -> None:
        """``options``: ``channel_type``, ``resolution``, ``depth_format``,
        ``experiment_name``, ``resume_experiment``, ``learning_type``,
        ``algorithm_mode``, ``connect``, ``env_id``, ``token``, ``rerun``,
        ``record``, ``twin_profile``, ``wait`` (see
        :func:`offworld_gym._config.resolve`)."""
        self._resolved = _config.resolve(task, realm, 1, render_mode=render_mode, **options)
        self._native = NativeEnvs(self._resolved.native)
        self._random_init = random_init
        self._last_rgb: np.ndarray | None = None
        #: Episode index within the experiment (kept out of ``info`` so that
        #: equal seeds give equal infos, as gymnasium's checker requires).
        self.episode_id: int | None = None
        self._closed = False
        self.render_mode = render_mode
        self.observation_space = _config.observation_space(self._resolved)
        self.action_space = _config.action_space(self._native.spec)

    @property
    def experiment_name(self) -> str:
        """The experiment this env records into."""
        return str(self._native.spec["experiment"])

    @property
    def experiment_id(self) -> int:
        """The store id of this env's experiment."""
        return int(self._native.spec["experiment_id"])

    def experiment(self) -> Experiment:
        """This env's experiment as the controller records it (counters
        include the episode in progress)."""
        found, _ = self._native.experiment_episodes()
        return found  # type: ignore[no-any-return]

    def episodes(self) -> list[Episode]:
        """Every episode of this env's experiment so far, in order, with its
        return, length, end reason and recordings (``record=``: paths are
        relative to that directory)."""
        _, episodes = self._native.experiment_episodes()
        return episodes  # type: ignore[no-any-return]

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Starts an episode; ``seed`` makes a sim episode reproducible."""
        super().reset(seed=seed)
        if seed is None and not self._random_init:
            seed = 0  # the original's random_init=False: always the same start
        observations, infos = self._native.reset([seed])
        obs, self._last_rgb = _config.split(self._resolved, observations[0])
        info = infos[0]
        # Kept out of info: gymnasium wants the same info for the same seed.
        self.episode_id = info.pop("episode_id")
        return obs, info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Executes one action on the robot (or its twin)."""
        obs, reward, terminated, truncated, info = self._native.step_without_autoreset(action)
        obs, self._last_rgb = _config.split(self._resolved, obs)
        self.episode_id = info.pop("episode_id")
        return obs, float(reward), bool(terminated), bool(truncated), info

    def render(self) -> np.ndarray | None:
        """The last RGB image (``render_mode="rgb_array"``)."""
        if self.render_mode != "rgb_array":
            return None
        return self._last_rgb

    def close(self) -> None:
        """Releases the lease; safe to call twice."""
        if not self._closed:
            self._closed = True
            self._native.close()
