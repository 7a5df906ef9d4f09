"""Bookings: reserve future time slots on an env (as the original service
had). During a slot only its holder can take the env's lease; outside slots
leases are first come, first served. A lease taken in a slot ends with it
(``offworld_gym.errors.Unauthorized`` saying so)."""

from __future__ import annotations

import datetime
import os
import time
from typing import TypedDict

from offworld_gym import _native
from offworld_gym._config import CONNECT_ENV, TOKEN_ENV
from offworld_gym.errors import ConfigurationError


class Booking(TypedDict):
    """One reserved slot ``[start, end)``."""

    id: int
    env_id: str
    user: str
    start_unix_ms: int
    end_unix_ms: int


When = datetime.datetime | float | int


def _unix_ms(when: When) -> int:
    """A datetime (naive = local time) or Unix seconds, as Unix ms."""
    if isinstance(when, datetime.datetime):
        return int(when.timestamp() * 1000)
    return int(float(when) * 1000)


def _token(token: str | None) -> str:
    token = token if token is not None else os.environ.get(TOKEN_ENV, "")
    if not token:
        raise ConfigurationError(f"bookings need an access token: pass token=… or set {TOKEN_ENV}")
    return token


def book(
    env_id: str, start: When, end: When, *, token: str | None = None, connect: str | None = None
) -> Booking:
    """Reserves ``[start, end)`` on ``env_id``; raises ``Busy`` if it overlaps
    another slot, ``BadRequest`` if it is empty, past, too long or too far ahead."""
    made = _native.book(env_id, _unix_ms(start), _unix_ms(end), _token(token), connect or os.environ.get(CONNECT_ENV))
    return made[0]  # type: ignore[return-value]


def bookings(env_id: str, *, since: When | None = None, connect: str | None = None) -> list[Booking]:
    """Slots of ``env_id`` that end after ``since`` (default: now), earliest first."""
    since_ms = _unix_ms(since) if since is not None else int(time.time() * 1000)
    return _native.bookings(env_id, since_ms, connect or os.environ.get(CONNECT_ENV))  # type: ignore[return-value]


def cancel_booking(
    env_id: str, booking_id: int, *, token: str | None = None, connect: str | None = None
) -> list[Booking]:
    """Cancels one of your slots (operators: any); returns the remaining ones."""
    return _native.cancel_booking(  # type: ignore[return-value]
        env_id, booking_id, _token(token), connect or os.environ.get(CONNECT_ENV)
    )


class Identity(TypedDict):
    """Who an access token is."""

    user: str
    #: Operators put envs into maintenance, revoke leases and press e-stops
    #: from the lab's web page.
    operator: bool


def whoami(*, env_id: str | None = None, token: str | None = None, connect: str | None = None) -> Identity:
    """Who ``token`` (default: ``OFFWORLD_GYM_ACCESS_TOKEN``) is, as the
    controller of ``env_id`` says (default: a real env's first, else any env's);
    ``Unauthorized`` for an unknown or revoked token."""
    return _native.whoami(env_id, _token(token), connect or os.environ.get(CONNECT_ENV))  # type: ignore[return-value]


def my_bookings(*, token: str | None = None, connect: str | None = None) -> list[Booking]:
    """Every slot booked with ``token`` (default: ``OFFWORLD_GYM_ACCESS_TOKEN``)
    on any env of the deployment that has not ended, earliest first."""
    return _native.my_bookings(_token(token), connect or os.environ.get(CONNECT_ENV))  # type: ignore[return-value]
