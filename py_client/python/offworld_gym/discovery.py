"""What a deployment offers: its envs, their tasks and availability."""

from __future__ import annotations

import os
from typing import TypedDict

from offworld_gym import _native
from offworld_gym._config import CONNECT_ENV
from offworld_gym.bookings import Booking
from offworld_gym.experiments import ResetAccuracy


class EnvInfo(TypedDict):
    """One env of a deployment."""

    env_id: str
    #: ``MonolithDiscrete`` etc.; empty when the env has no live controller.
    task: str
    #: ``free``, ``leased``, ``maintenance`` or ``offline``.
    state: str
    #: Lease expiry (Unix ms) while ``leased``; the operator's expected end
    #: of a ``maintenance``, when they said one.
    until_unix_ms: int | None
    #: Maintenance message or why the env is offline.
    message: str
    #: Who holds the lease (``leased``) or put the env into ``maintenance``.
    who: str | None
    #: Live components: ``controller``, ``sim_twin``, ``robot_agent``, …
    components: list[str]
    #: Booked slots in progress or ahead, earliest first.
    bookings: list[Booking]
    #: E-stops in force: ``{"site": reason, "env": reason}`` for the engaged
    #: latches (motion is refused while any is); empty when none.
    estops: dict[str, str]
    #: How well the env's last reset put the robot at its spawn pose; None
    #: before its first reset (or when its controller does not answer).
    last_reset: ResetAccuracy | None


def list_envs(connect: str | None = None, timeout: float = 2.0) -> list[EnvInfo]:
    """Lists the envs reachable through ``connect`` (or ``OFFWORLD_GYM_CONNECT``;
    the Zenoh config file in ``OFFWORLD_ZENOH_CONFIG`` supplies TLS and
    credentials), sorted by env id."""
    connect = connect or os.environ.get(CONNECT_ENV)
    return _native.list_envs(connect, timeout)  # type: ignore[return-value]
