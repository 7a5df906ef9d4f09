"""Gymnasium registration of every OffWorld id, current and legacy spellings."""

from __future__ import annotations

import gymnasium

_ENTRY = "offworld_gym.envs.offworld_monolith:OffWorldMonolithEnv"
_VECTOR_ENTRY = "offworld_gym.envs.vector:OffWorldMonolithVectorEnv"


def _ids() -> dict[str, tuple[str, str]]:
    ids: dict[str, tuple[str, str]] = {}
    for world in ("Monolith", "MonolithObstacle"):
        for action in ("Discrete", "Continuous"):
            for realm in ("Real", "Sim"):
                ids[f"OffWorld{world}{action}{realm}-v0"] = (f"{world}{action}", realm.lower())
    return ids


#: id -> (task, realm) for the eight current ids.
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
