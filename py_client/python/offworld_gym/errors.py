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
