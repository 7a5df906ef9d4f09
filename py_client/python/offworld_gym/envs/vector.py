"""Native vector env: N twins stepped concurrently, one fan-out per step."""

from __future__ import annotations

from typing import Any, Sequence

import gymnasium
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from offworld_gym import _config
from offworld_gym._native import NativeEnvs


class OffWorldMonolithVectorEnv(VectorEnv):
    """``gymnasium.make_vec(id, num_envs=N)``: next-step autoreset, like gymnasium 1.x.

    Ctrl-C during a call raises ``KeyboardInterrupt`` and leaves the envs
    usable, as for :class:`~offworld_gym.envs.offworld_monolith.OffWorldMonolithEnv`:
    call ``reset()`` before stepping again.
    """

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int,
        task: str,
        realm: str,
        render_mode: str | None = None,
        max_episode_steps: int | None = None,
        random_init: bool = True,
        **options: Any,
    ) -> None:
        """``options`` as for :class:`OffWorldMonolithEnv`; with one ``env_id``
        and N envs, remote envs are ``<env_id>-0 … <env_id>-(N-1)``."""
        self._resolved = _config.resolve(task, realm, num_envs, render_mode=render_mode, **options)
        self._native = NativeEnvs(self._resolved.native)
        self._closed = False
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.single_observation_space = _config.observation_space(self._resolved)
        self.single_action_space = _config.action_space(self._native.spec)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)

    def _infos(self, infos: list[dict[str, Any]]) -> dict[str, Any]:
        """Per-key arrays with gymnasium's ``_key`` masks (see ``docs/info.md``)."""
        #: Episode index per env (kept out of ``info``, as in the single env).
        self.episode_ids = np.array([i["episode_id"] for i in infos], dtype=np.int64)
        every = np.ones(self.num_envs, dtype=bool)
        batched: dict[str, Any] = {
            "step": np.array([i["step"] for i in infos], dtype=np.int64),
            "is_success": np.array([i["is_success"] for i in infos], dtype=bool),
            "end_reason": np.array([i["end_reason"] for i in infos], dtype=object),
        }
        for key in list(batched):
            batched[f"_{key}"] = every
        shared = np.array(["pose" in i for i in infos], dtype=bool)
        if shared.any():
            batched["pose"] = np.array([i.get("pose", (0.0, 0.0, 0.0)) for i in infos], dtype=np.float64)
            batched["distance_to_goal"] = np.array([i.get("distance_to_goal", 0.0) for i in infos], dtype=np.float64)
            batched["_pose"] = batched["_distance_to_goal"] = shared
        return batched

    def _requested(self, observations: np.ndarray) -> np.ndarray:
        """The requested channels of the native stack (one array, envs first)."""
        return np.ascontiguousarray(_config.requested(self._resolved, observations))

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Resets every env; an int seed gives env i the seed ``seed + i``."""
        if seed is None:
            seeds: list[int | None] = [None] * self.num_envs
        elif isinstance(seed, int):
            seeds = [seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
        observations, infos = self._native.reset(seeds)
        return self._requested(observations), self._infos(infos)

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Steps all envs at once; an env whose episode ended last step is reset instead."""
        observations, results = self._native.step_with_autoreset([actions[i] for i in range(self.num_envs)])
        obs = self._requested(observations)
        rewards = np.array([r[0] for r in results], dtype=np.float64)
        terminated = np.array([r[1] for r in results], dtype=bool)
        truncated = np.array([r[2] for r in results], dtype=bool)
        return obs, rewards, terminated, truncated, self._infos([r[3] for r in results])

    def close_extras(self, **kwargs: Any) -> None:
        """Releases every lease."""
        if not self._closed:
            self._closed = True
            self._native.close()
