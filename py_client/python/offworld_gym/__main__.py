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

Credentials: ``OFFWORLD_GYM_ACCESS_TOKEN`` (or ``--token``); TLS and Zenoh
user/password from the config file in ``OFFWORLD_ZENOH_CONFIG``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import sys

from offworld_gym.bookings import Booking, book, bookings, cancel_booking, my_bookings, whoami
from offworld_gym.discovery import list_envs
from offworld_gym.errors import OffWorldGymError
from offworld_gym.experiments import ResetAccuracy, experiment, experiments, leaderboard


def _when(unix_ms: int | None) -> str:
    if unix_ms is None:
        return ""
    return datetime.datetime.fromtimestamp(unix_ms / 1000, tz=datetime.timezone.utc).isoformat(timespec="seconds")


def _reset(reset: ResetAccuracy) -> str:
    """``3.2 cm 1.4° 41.5 s``: how far from its spawn pose a reset left the robot, and how long it took."""
    return (
        f"{reset['position_error_m'] * 100:.1f} cm {math.degrees(reset['yaw_error_rad']):.1f}° {reset['duration_s']:.1f} s"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m offworld_gym", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    envs = sub.add_parser("envs", help="list envs, their tasks and availability")
    envs.add_argument("--connect", help="Zenoh endpoint (default: OFFWORLD_GYM_CONNECT)")
    envs.add_argument("--timeout", type=float, default=2.0, help="seconds per query")
    envs.add_argument("--json", action="store_true", help="print JSON")
    listing = sub.add_parser("bookings", help="list an env's booked slots, or yours on every env (--mine)")
    listing.add_argument("--mine", action="store_true", help="your slots on every env (needs your token)")
    who = sub.add_parser("whoami", help="who your access token is, and whether you are an operator")
    who.add_argument("--connect", help="Zenoh endpoint (default: OFFWORLD_GYM_CONNECT)")
    who.add_argument("--json", action="store_true", help="print JSON")
    made = sub.add_parser("book", help="reserve a slot on an env")
    made.add_argument("--start", required=True, help="ISO time, e.g. 2026-12-01T14:00 (local) or …Z")
    made.add_argument("--minutes", type=float, required=True, help="slot length")
    cancel = sub.add_parser("cancel-booking", help="cancel one of your slots")
    cancel.add_argument("--id", type=int, required=True, help="booking id (see `bookings`)")
    mine = sub.add_parser("experiments", help="list your experiments on an env (operators: all)")
    shown = sub.add_parser("episodes", help="the episodes of one experiment, with their recordings")
    shown.add_argument("--id", type=int, required=True, help="experiment id (see `experiments`)")
    board = sub.add_parser("leaderboard", help="an env's test-mode experiments, best first")
    for p in (listing, made, cancel, mine, shown, board):
        # `bookings --mine` needs no env.
        p.add_argument("--env", required=p is not listing, help="env id, e.g. real/monolith-0")
        p.add_argument("--connect", help="Zenoh endpoint (default: OFFWORLD_GYM_CONNECT)")
        p.add_argument("--json", action="store_true", help="print JSON")
    for p in (listing, made, cancel, mine, shown, who):
        p.add_argument("--token", help="access token (default: OFFWORLD_GYM_ACCESS_TOKEN)")
    args = parser.parse_args(argv)
    if args.command == "bookings" and not args.mine and not args.env:
        parser.error("bookings: say which env (--env ENV_ID) or ask for yours (--mine)")
    try:
        if args.command == "whoami":
            return _whoami_command(args)
        if args.command in ("experiments", "episodes", "leaderboard"):
            return _records_command(args)
        if args.command != "envs":
            return _bookings_command(args)
        listed = list_envs(args.connect, args.timeout)
    except (OffWorldGymError, ValueError, LookupError, PermissionError, ConnectionError, TimeoutError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(listed, indent=1))
        return 0
    for env in listed:
        state = env["state"]
        if state == "leased":
            state += f" by {env.get('who')} until {_when(env['until_unix_ms'])}"
        elif env["message"]:
            state += f" ({env['message']})"
            if state.startswith("maintenance") and env.get("until_unix_ms"):
                state += f" back at {_when(env['until_unix_ms'])}"
        for latch, reason in env.get("estops", {}).items():
            state += f" E-STOP {latch} ({reason})"
        print(f"{env['env_id']:<28} {env['task'] or '-':<26} {state:<40} {','.join(env['components'])}")
        reset = env.get("last_reset")
        if reset:
            print(f"    last reset {_reset(reset)}")
        for slot in env["bookings"]:
            print(f"    booked by {slot['user']} {_when(slot['start_unix_ms'])} – {_when(slot['end_unix_ms'])}")
    if not listed:
        print("no envs found", file=sys.stderr)
    return 0


def _bookings_command(args: argparse.Namespace) -> int:
    slots: list[Booking]
    if args.command == "book":
        start = datetime.datetime.fromisoformat(args.start)
        end = start + datetime.timedelta(minutes=args.minutes)
        slots = [book(args.env, start, end, token=args.token, connect=args.connect)]
    elif args.command == "cancel-booking":
        slots = cancel_booking(args.env, args.id, token=args.token, connect=args.connect)
    elif args.mine:
        slots = my_bookings(token=args.token, connect=args.connect)
    else:
        slots = bookings(args.env, connect=args.connect)
    if args.json:
        print(json.dumps(slots, indent=1))
        return 0
    for b in slots:
        print(f"{b['id']:>5}  {b['env_id']:<24} {_when(b['start_unix_ms'])} .. {_when(b['end_unix_ms'])}  {b['user']}")
    if not slots and args.command == "bookings":
        print("nothing booked", file=sys.stderr)
    return 0


def _whoami_command(args: argparse.Namespace) -> int:
    me = whoami(token=args.token, connect=args.connect)
    if args.json:
        print(json.dumps(me))
    else:
        print(f"{me['user']}{' (operator)' if me['operator'] else ''}")
    return 0


def _records_command(args: argparse.Namespace) -> int:
    if args.command == "experiments":
        found = experiments(args.env, token=args.token, connect=args.connect)
        if args.json:
            print(json.dumps(found, indent=1))
            return 0
        print(f"{'id':>5}  {'user':<12} {'experiment':<28} {'type':<10} {'mode':<5} {'episodes':>8} {'steps':>8}  last used")
        for e in found:
            print(
                f"{e['id']:>5}  {e['user']:<12} {e['name']:<28} {e['learning_type']:<10} {e['algorithm_mode']:<5} "
                f"{e['episodes']:>8} {e['steps']:>8}  {_when(e['updated_unix_ms'])}"
            )
        return 0
    if args.command == "episodes":
        found_experiment, episodes = experiment(args.env, args.id, token=args.token, connect=args.connect)
        if args.json:
            print(json.dumps({"experiment": found_experiment, "episodes": episodes}, indent=1))
            return 0
        print(f"experiment {found_experiment['id']} {found_experiment['name']!r} of {found_experiment['user']}")
        print(f"{'episode':>7} {'steps':>5} {'return':>8}  {'end':<32} {'reset: off by, took':<24} recording")
        for ep in episodes:
            files = ", ".join(r["path"] + ("" if r["complete"] else " (partial)") for r in ep["recordings"])
            reset = _reset(ep["reset"]) if ep["reset"] else "-"
            print(
                f"{ep['index']:>7} {ep['steps']:>5} {ep['episode_return']:>8.3f}  {ep['end_reason']:<32} {reset:<24} {files or '-'}"
            )
        return 0
    ranked = leaderboard(args.env, connect=args.connect)
    if args.json:
        print(json.dumps(ranked, indent=1))
        return 0
    print(f"{'rank':>4}  {'experiment':<28} {'user':<12} {'type':<10} {'episodes':>8} {'success':>8} {'return':>8}")
    for r in ranked:
        print(
            f"{r['rank']:>4}  {r['experiment']:<28} {r['user']:<12} {r['learning_type']:<10} {r['episodes']:>8} "
            f"{r['success_rate'] * 100:>7.1f}% {r['mean_return']:>8.3f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
