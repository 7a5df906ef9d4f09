"""Exceptions raised by offworld_gym.

Server errors carry the server's typed code (``err.code``) and message;
each code has its own class. Every class derives from ``OffWorldGymError`` (itself a ``RuntimeError``),
and from the builtin that fits where there is one:

======================  ====  =====================================
class                   code  also a
======================  ====  =====================================
``BadRequest``          400   ``ValueError``
``Unauthorized``        401   ``PermissionError``
``NotFound``            404   ``LookupError``
``Busy``                409   —
``InvalidState``        412   —
``Unavailable``         503   ``ConnectionError``
``Timeout``             504   ``TimeoutError``
``Internal``            500   —
``ConfigurationError``  —     ``ValueError`` (raised before anything is sent)
======================  ====  =====================================

``Busy`` means "not now, someone else first": the env is leased or booked
by someone else, or the controller is at one of its request limits (this
env's queue is full, or this client has too many requests queued or sends
them too fast). Nothing was done; the message says which and when to retry.
"""


class OffWorldGymError(RuntimeError):
    """Base of every offworld_gym error. ``code`` is the server's error code
    (400, 401, …) when the server refused; None for a local failure."""

    code: int | None = None


class BadRequest(OffWorldGymError, ValueError):
    """The request or action is invalid (code 400)."""

    code = 400


class Unauthorized(OffWorldGymError, PermissionError):
    """Missing or wrong token, lease or booking (401)."""

    code = 401


class NotFound(OffWorldGymError, LookupError):
    """No such env, session or experiment (404)."""

    code = 404


class Busy(OffWorldGymError):
    """The env is leased or booked by someone else, or the controller is at a
    request limit (409): nothing was done; retry later."""

    code = 409


class InvalidState(OffWorldGymError):
    """Not now: step before reset, after the end (412)."""

    code = 412


class Unavailable(OffWorldGymError, ConnectionError):
    """Maintenance, offline, e-stopped, or tracking lost (503)."""

    code = 503


class Timeout(OffWorldGymError, TimeoutError):
    """A component did not answer in time (504)."""

    code = 504


class Internal(OffWorldGymError):
    """A server-side failure (500)."""

    code = 500


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
