"""``python -m offworld_gym``: what a deployment offers, from the command line.

    python -m offworld_gym envs --connect quic/router.example:7447
    python -m offworld_gym bookings --env real/monolith-0
    python -m offworld_gym bookings --mine
    python -m offworld_gym whoami
    python -m offworld_gym book --env real/monolith-0 --start 2026-12-01T14:00 --minutes 60
    python -m offworld_gym cancel-booking --env real/monolith-0 --id 3
    python -m offworld_gym experiments --env real/monolith-0
    python -m offworld_gym episodes --env real/monolith-0 --id 12
    python -m offworld_gym leaderboard --env real/monolith-0

The same commands as ``offworld gym …`` (one implementation, in Rust).
Credentials: ``OFFWORLD_GYM_ACCESS_TOKEN`` (or ``--token``); TLS and Zenoh
user/password from the config file in ``OFFWORLD_ZENOH_CONFIG``.
"""

from __future__ import annotations

import signal
import sys

from offworld_gym import _native


def main(argv: list[str] | None = None) -> int:
    """Runs one command (``argv`` without the program, default ``sys.argv[1:]``);
    returns its exit status. It prints on the process's stdout and stderr."""
    return _native.run_command_line(["python -m offworld_gym", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    # A native command: Ctrl-C ends it at once, as it would `offworld gym`
    # (only as a program: an interpreter that calls `main` keeps its handler).
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    sys.exit(main())
