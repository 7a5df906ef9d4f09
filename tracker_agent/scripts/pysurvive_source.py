#!/usr/bin/env python3
r"""Stream Vive tracker poses from libsurvive as tracker_agent protocol lines.

    python3 pysurvive_source.py [--only SERIAL] [--unix-time] [libsurvive args...] \
        | offworld tracker run --env real/monolith-0 --source stdin --calibration tracker.toml

Each tracked device update becomes one line on stdout (flushed at once):

    <device_id> <timestamp_s> <x> <y> <z> <qx> <qy> <qz> <qw>

- device_id: the device's serial number (e.g. LHR-1A2B3C4D) when libsurvive
  reports one, else its name (T20, WM0, ...); pass it to `offworld tracker
  run --device` when several devices are tracked.
- timestamp_s: libsurvive's pose time (seconds, monotonic), or the host's
  unix time with --unix-time.
- position in metres and orientation in libsurvive's tracking frame;
  libsurvive's SurvivePose.Rot is (w, x, y, z), reordered here to the
  protocol's x y z w.

Lighthouses (base stations) are skipped, and so are repeated updates with an
unchanged pose time. Other arguments go to libsurvive (pysurvive.SimpleContext).
Needs libsurvive's Python bindings: `pip install pysurvive`.
"""

import re
import sys
import time


def _text(value):
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    return str(value)


def _device_id(pysurvive, obj):
    """A whitespace-free, non-numeric token naming the device."""
    ident = ""
    serial = getattr(pysurvive, "simple_serial_number", None)
    if serial is not None:
        try:
            ident = _text(serial(obj.ptr) or "")
        except Exception:  # older bindings: fall back to the name
            ident = ""
    if not ident:
        ident = _text(obj.Name())
    ident = re.sub(r"\s+", "_", ident.strip()) or "device"
    try:
        float(ident)
        return "dev-" + ident  # a numeric id would read as a timestamp
    except ValueError:
        return ident


def _is_lighthouse(pysurvive, obj):
    get_type = getattr(pysurvive, "simple_object_get_type", None)
    lighthouse = getattr(pysurvive, "SurviveSimpleObject_LIGHTHOUSE", None)
    if get_type is not None and lighthouse is not None:
        try:
            return get_type(obj.ptr) == lighthouse
        except Exception:
            pass
    # libsurvive names base stations LH0, LH1, ...
    return re.fullmatch(r"LH\d+", _text(obj.Name())) is not None


def _split_args(argv):
    """Our options out of argv; the rest goes to libsurvive."""
    only, unix_time, rest = None, False, [argv[0]]
    args = iter(argv[1:])
    for arg in args:
        if arg == "--only":
            only = next(args, None)
        elif arg.startswith("--only="):
            only = arg.split("=", 1)[1]
        elif arg == "--unix-time":
            unix_time = True
        else:
            rest.append(arg)
    return only, unix_time, rest


def main(argv):
    if any(arg in ("-h", "--help") for arg in argv[1:]):
        print(__doc__.strip())
        return 0
    only, unix_time, survive_args = _split_args(argv)
    try:
        import pysurvive  # imported here: --help works without libsurvive
    except ImportError as e:
        print(
            "pysurvive_source.py: libsurvive's Python bindings are missing (%s): "
            "`pip install pysurvive`, then run again" % e,
            file=sys.stderr,
        )
        return 2

    ctx = pysurvive.SimpleContext(survive_args)
    last_time = {}
    ids = {}
    while ctx.Running():
        updated = ctx.NextUpdated()
        if not updated:
            continue
        name = _text(updated.Name())
        if name not in ids:
            ids[name] = None if _is_lighthouse(pysurvive, updated) else _device_id(pysurvive, updated)
            if ids[name] is not None:
                print("# device %s (%s)" % (ids[name], name), file=sys.stderr, flush=True)
        device = ids[name]
        if device is None or (only is not None and only not in (device, name)):
            continue
        pose, pose_time = updated.Pose()
        if pose_time <= 0 or last_time.get(device) == pose_time:
            continue  # no pose yet, or nothing new
        last_time[device] = pose_time
        stamp = time.time() if unix_time else pose_time
        x, y, z = (float(v) for v in pose.Pos[:3])
        qw, qx, qy, qz = (float(v) for v in pose.Rot[:4])
        try:
            print(
                "%s %.6f %.6f %.6f %.6f %.9f %.9f %.9f %.9f"
                % (device, stamp, x, y, z, qx, qy, qz, qw),
                flush=True,
            )
        except BrokenPipeError:
            return 0  # the agent went away
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv))
    except KeyboardInterrupt:
        sys.exit(0)
