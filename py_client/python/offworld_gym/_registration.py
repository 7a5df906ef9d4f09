"""Gymnasium registration of every OffWorld id, current and legacy spellings."""

from __future__ import annotations

import gymnasium

from offworld_gym import _native

_ENTRY = "offworld_gym.envs.offworld_monolith:OffWorldMonolithEnv"
_VECTOR_ENTRY = "offworld_gym.envs.vector:OffWorldMonolithVectorEnv"


def _ids() -> dict[str, tuple[str, str]]:
    """`OffWorld<task><Realm>-v0` for every task of the controller's table."""
    return {
        f"OffWorld{task}{realm.capitalize()}-v0": (task, realm)
        for task in _native.task_names()
        for realm in ("real", "sim")
    }


#: id -> (task, realm) for the current ids (eight: two worlds × two action
#: spaces × real and sim).
ENV_IDS: dict[str, tuple[str, str]] = _ids()

#: Spellings found in users' scripts of the original OffWorld Gym.
LEGACY_IDS: dict[str, tuple[str, str]] = {
    "OffWorldMonolithContinousSim-v0": ("MonolithContinuous", "sim"),
    "OffWorldMonolithContinousReal-v0": ("MonolithContinuous", "real"),
    "OffWorldMonolithObstacleContinousSim-v0": ("MonolithObstacleContinuous", "sim"),
    "OffWorldMonolithObstacleContinousReal-v0": ("MonolithObstacleContinuous", "real"),
    "OffWorldDockerMonolithDiscreteSim-v0": ("MonolithDiscrete", "sim"),
    "OffWorldDockerMonolithContinuousSim-v0": ("MonolithContinuous", "sim"),
}


def register_envs() -> None:
    """Registers every id (idempotent)."""
    for env_id, (task, realm) in {**ENV_IDS, **LEGACY_IDS}.items():
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id,
            entry_point=_ENTRY,
            vector_entry_point=_VECTOR_ENTRY,
            kwargs={"task": task, "realm": realm},
        )
