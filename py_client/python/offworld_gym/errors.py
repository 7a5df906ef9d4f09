"""Exceptions raised by offworld_gym.

Server errors carry the server's typed code (``err.code``) and message;
each code has its own class:

====================  ====  =====================================
class                 code  also a
====================  ====  =====================================
``BadRequest``        400   ``ValueError``
``Unauthorized``      401   ``PermissionError``
``NotFound``          404   ``LookupError``
``Busy``              409   ``OffWorldGymError``
``InvalidState``      412   ``OffWorldGymError``
``Unavailable``       503   ``ConnectionError``
``Timeout``           504   ``TimeoutError``
``Internal``          500   ``OffWorldGymError``
====================  ====  =====================================

``Busy`` means "not now, someone else first": the env is leased or booked
by someone else, or the controller is at one of its request limits (this
env's queue is full, or this client has too many requests queued or sends
them too fast). Nothing was done; the message says which and when to retry.
"""

from offworld_gym._native import (
    BadRequest,
    Busy,
    Internal,
    InvalidState,
    NotFound,
    OffWorldGymError,
    Timeout,
    Unauthorized,
    Unavailable,
)


class ConfigurationError(OffWorldGymError, ValueError):
    """The env cannot be created as configured (e.g. a real id without a deployment or token)."""


__all__ = [
    "BadRequest",
    "Busy",
    "ConfigurationError",
    "Internal",
    "InvalidState",
    "NotFound",
    "OffWorldGymError",
    "Timeout",
    "Unauthorized",
    "Unavailable",
]
