"""OffWorld Gym on Zenoh: real-world RL on physical robots and their twins.

``import offworld_gym`` registers the gymnasium ids::

    import gymnasium
    import offworld_gym
    from offworld_gym.envs.common.channels import Channels

    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", channel_type=Channels.DEPTH_ONLY)

``…Sim-v0`` ids start an embedded sim deployment inside this process unless
``connect=`` (or ``OFFWORLD_GYM_CONNECT``) names a remote one; ``…Real-v0``
ids need a deployment and an access token (``OFFWORLD_GYM_ACCESS_TOKEN``).
"""

from offworld_gym import errors
from offworld_gym._native import __version__
from offworld_gym._registration import ENV_IDS, LEGACY_IDS, register_envs
from offworld_gym.bookings import Booking, Identity, book, bookings, cancel_booking, my_bookings, whoami
from offworld_gym.discovery import EnvInfo, list_envs
from offworld_gym.envs.common.channels import Channels
from offworld_gym.envs.common.enums import AlgorithmMode, LearningType
from offworld_gym.experiments import (
    Episode,
    Experiment,
    LeaderboardEntry,
    Recording,
    ResetAccuracy,
    experiment,
    experiments,
    leaderboard,
)

register_envs()

__all__ = [
    "ENV_IDS",
    "LEGACY_IDS",
    "AlgorithmMode",
    "Booking",
    "Channels",
    "EnvInfo",
    "Episode",
    "Experiment",
    "Identity",
    "LeaderboardEntry",
    "LearningType",
    "Recording",
    "ResetAccuracy",
    "__version__",
    "book",
    "bookings",
    "cancel_booking",
    "errors",
    "experiment",
    "experiments",
    "leaderboard",
    "list_envs",
    "my_bookings",
    "register_envs",
    "whoami",
]
