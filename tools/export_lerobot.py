#!/usr/bin/env python3
"""Export recorded episodes (MCAP, docs/recording.md) to a LeRobot v3.0 dataset.

    PY=$(tools/lerobot-venv)
    "$PY" tools/export_lerobot.py DIR OUT --repo-id offworld/NAME [--fps N] [--videos]

Runs in the LeRobot venv (tools/lerobot-venv; lerobot==0.4.4 cannot live in the
project's main Python env). Reads every complete `*.mcap` under DIR
(recursively; `*.mcap.partial` files are skipped and listed: turn one into a
complete file with `recorder recover` first) with `mcap` + mcap-ros2-support,
and writes one LeRobot episode per file with lerobot's own writer, episodes
ordered by (env_id, experiment_id, episode_id) of their EpisodeInfo.

Frames. An episode file holds the Steps s0 (the reset, step = 0), s1 .. sN.
LeRobot frame i (i = 0 .. N-1) pairs the observation of s_i with the action
taken from it, which is the command of s_{i+1}, and that command's outcome:

  observation.images.color     image (H, W, 3) uint8: /camera/color/image_raw of s_i (rgb8;
                               bgr8 is converted); a `video` feature with --videos
  observation.depth            float32 (H, W), metres: /camera/depth/image_raw of s_i;
                               32FC1 as is, 16UC1 millimetres / 1000; every value that is
                               not finite (NaN = no return) becomes 0, like 16UC1's 0 (no
                               return). Kept numeric (exact) in both modes: LeRobot 0.4.4
                               images and videos must have 3 channels.
  observation.state            float32 (8,) [x, y, yaw, odom_x, odom_y, odom_yaw, odom_vx,
                               odom_wz]: x, y, yaw of /tracker/pose of s_i (yaw from the
                               quaternion, about z), then the latest /odom whose
                               header.stamp <= s_i's capture time (pose position x, y,
                               yaw, twist linear.x, angular.z); all zero when there is none
  observation.capture_time_s   float64 (1,): s_i.header.stamp (sec + nanosec / 1e9), exact in
                               the parquet files; NOTE LeRobotDataset.__getitem__ turns
                               (1,)-features into torch.tensor(python float) = float32
                               (~2 min resolution at today's Unix times), so
  observation.capture_time_ns  int64 (1,): the same stamp in integer nanoseconds, exact
                               through LeRobotDataset too
  action                       float32 (2,) [linear_x m/s, angular_z rad/s] of s_{i+1}
  action.discrete              int64 (1,): s_{i+1}.action_discrete (-1 = continuous)
  action.normalized            float32 (2,): s_{i+1}.action_continuous [linear, angular]
                               in [-1, 1], zeros when discrete
  next.reward                  float32 (1,): s_{i+1}.reward
  next.done                    bool (1,): s_{i+1}.terminated or s_{i+1}.truncated
  next.truncated, next.success bool (1,): s_{i+1}.truncated, s_{i+1}.success
  task                         EpisodeInfo.task (env_id when empty)

The last observation (of sN) has no action and is not a frame, so an episode
of N steps is N frames; an episode with no step after its reset is skipped.
A step's color, depth and pose are the ones written between the previous Step
message and its own (the Step message is the last of its step, in file
order); odometry is matched by stamp. LeRobot's `timestamp` is
frame_index / fps (what its video lookup needs); the real capture time is
`observation.capture_time_s`. fps = --fps, else round(1 / median step period
over all episodes), at least 1.

Also written: meta/offworld_episodes.jsonl, one line per LeRobot episode
(episode_index, source file relative to DIR, env_id, experiment_id,
episode_id, seed, end_reason, ...). LeRobot ignores it.

The dataset is built in a sibling directory OUT.partial-<pid> and renamed to
OUT when complete. Exit codes: 0 done; 1 a bad file (every problem is listed
before anything is written; --skip-bad skips such files instead) or a failed
write; 2 usage: DIR missing, OUT exists, no episode to export.

--videos encodes the color images as video (lossy, default codec libsvtav1 via
PyAV). To load such a dataset here pass `video_backend="pyav"` to
LeRobotDataset: torchcodec, lerobot's default decoder, needs FFmpeg's shared
libraries on the system.
"""

from __future__ import annotations

import argparse
import bisect
import json
import math
import os
import shutil
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

TOPIC_INFO = "/offworld/episode"
TOPIC_COLOR = "/camera/color/image_raw"
TOPIC_DEPTH = "/camera/depth/image_raw"
TOPIC_POSE = "/tracker/pose"
TOPIC_ODOM = "/odom"
TOPIC_STEP = "/offworld/step"
TOPIC_END = "/offworld/episode_end"

STATE_NAMES = ["x", "y", "yaw", "odom_x", "odom_y", "odom_yaw", "odom_vx", "odom_wz"]
ROBOT_TYPE = "rosbot"


class UsageError(Exception):
    """Exit code 2."""


class BadFile(Exception):
    """A file that cannot be exported as an episode."""


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ------------------------------------------------------------- decoding

def stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def stamp_s(header) -> float:
    return int(header.stamp.sec) + int(header.stamp.nanosec) / 1e9


def yaw_of(q) -> float:
    """Yaw (rotation about z) of a quaternion, radians."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _pixel_rows(img, bytes_per_pixel: int) -> np.ndarray:
    """(height, width * bytes_per_pixel) uint8 view of an Image's data, honouring `step`."""
    h, w, step = int(img.height), int(img.width), int(img.step)
    row = w * bytes_per_pixel
    buf = np.frombuffer(bytes(img.data), dtype=np.uint8)
    if step < row or buf.size < h * step:
        raise BadFile(f"image {w}x{h} {img.encoding}: step {step}, {buf.size} bytes")
    return buf[: h * step].reshape(h, step)[:, :row]


def color_rgb(img) -> np.ndarray:
    """sensor_msgs/Image rgb8 | bgr8 -> (H, W, 3) uint8 RGB."""
    enc = img.encoding
    if enc not in ("rgb8", "bgr8"):
        raise BadFile(f"color image encoding {enc!r} (want rgb8)")
    arr = _pixel_rows(img, 3).reshape(int(img.height), int(img.width), 3)
    if enc == "bgr8":
        arr = arr[:, :, ::-1]
    return np.ascontiguousarray(arr)


def depth_m(img) -> np.ndarray:
    """sensor_msgs/Image 32FC1 (m) | 16UC1 (mm) -> (H, W) float32 metres, no return = 0."""
    enc = img.encoding
    h, w = int(img.height), int(img.width)
    order = ">" if img.is_bigendian else "<"
    if enc == "32FC1":
        arr = _pixel_rows(img, 4).copy().view(order + "f4").reshape(h, w).astype(np.float32)
        arr[~np.isfinite(arr)] = 0.0
        return arr
    if enc in ("16UC1", "mono16"):
        mm = _pixel_rows(img, 2).copy().view(order + "u2").reshape(h, w)
        return mm.astype(np.float32) / np.float32(1000.0)
    raise BadFile(f"depth image encoding {enc!r} (want 32FC1 or 16UC1)")


# ------------------------------------------------------------- scanning

@dataclass
class StepInfo:
    step: int
    stamp_ns: int
    capture_time_s: float
    linear_x: float
    angular_z: float
    action_discrete: int
    action_continuous: list
    reward: float
    terminated: bool
    truncated: bool
    success: bool
    end_reason: str
    pose: tuple  # x, y, yaw


@dataclass
class EpisodeScan:
    path: Path
    info: dict
    steps: list = field(default_factory=list)          # StepInfo, s0..sN
    odom_stamps: list = field(default_factory=list)    # sorted ns
    odom_values: list = field(default_factory=list)    # (x, y, yaw, vx, wz)
    color_shape: tuple | None = None
    depth_shape: tuple | None = None
    depth_encoding: str = ""
    end: dict | None = None
    notes: list = field(default_factory=list)

    @property
    def key(self):
        return (self.info["env_id"], self.info["experiment_id"], self.info["episode_id"], str(self.path))

    def odom_at(self, t_ns: int) -> tuple:
        i = bisect.bisect_right(self.odom_stamps, t_ns) - 1
        return self.odom_values[i] if i >= 0 else (0.0, 0.0, 0.0, 0.0, 0.0)


class _Decoders:
    """Decoders of one file, by channel id. A new DecoderFactory per file: it
    caches decoders by schema id, and schema ids are per file."""

    def __init__(self):
        from mcap_ros2.decoder import DecoderFactory

        self.factory = DecoderFactory()
        self.by_channel: dict = {}

    def decode(self, schema, channel, message):
        dec = self.by_channel.get(channel.id)
        if dec is None:
            dec = self.factory.decoder_for(channel.message_encoding, schema)
            if dec is None:
                raise BadFile(f"{channel.topic}: cannot decode {channel.message_encoding!r} with "
                              f"schema encoding {schema.encoding if schema else None!r} "
                              "(want cdr + ros2msg)")
            self.by_channel[channel.id] = dec
        return dec(message.data)


def _reader(f):
    from mcap.reader import make_reader

    return make_reader(f)


def scan_episode(path: Path) -> EpisodeScan:
    """Reads everything but the pixels; checks the structure."""
    with open(path, "rb") as f:
        reader = _reader(f)
        header = reader.get_header()
        if header.profile != "ros2":
            raise BadFile(f"MCAP profile {header.profile!r}, not 'ros2'")
        dec = _Decoders()
        info = None
        scan = None
        group = {TOPIC_COLOR: 0, TOPIC_DEPTH: 0}
        pose = None
        odom = []
        trailing = []
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            topic = channel.topic
            if topic == TOPIC_INFO:
                if info is not None:
                    raise BadFile("two EpisodeInfo messages")
                m = dec.decode(schema, channel, message)
                info = {k: getattr(m, k) for k in (
                    "env_id", "task", "world", "experiment_id", "experiment", "learning_type",
                    "algorithm_mode", "episode_id", "seeded", "seed", "embodiment",
                    "software_version", "max_episode_steps")}
                info["experiment_id"] = int(info["experiment_id"])
                info["episode_id"] = int(info["episode_id"])
                info["seed"] = int(info["seed"])
                info["max_episode_steps"] = int(info["max_episode_steps"])
                scan = EpisodeScan(path=path, info=info)
                continue
            if scan is None:
                if topic in (TOPIC_STEP, TOPIC_COLOR, TOPIC_DEPTH, TOPIC_POSE):
                    raise BadFile(f"{topic} before the EpisodeInfo")
                if topic != TOPIC_ODOM:
                    continue
            if topic in (TOPIC_COLOR, TOPIC_DEPTH):
                group[topic] += 1
                if topic == TOPIC_COLOR and scan.color_shape is None:
                    img = dec.decode(schema, channel, message)
                    scan.color_shape = color_rgb(img).shape
                if topic == TOPIC_DEPTH and scan.depth_shape is None:
                    img = dec.decode(schema, channel, message)
                    scan.depth_shape = depth_m(img).shape
                    scan.depth_encoding = img.encoding
            elif topic == TOPIC_POSE:
                m = dec.decode(schema, channel, message)
                if pose is not None:
                    raise BadFile(f"two poses in step {len(scan.steps)}")
                p = m.pose
                pose = (float(p.position.x), float(p.position.y), yaw_of(p.orientation))
            elif topic == TOPIC_ODOM:
                m = dec.decode(schema, channel, message)
                p, tw = m.pose.pose, m.twist.twist
                odom.append((stamp_ns(m.header), len(odom), (
                    float(p.position.x), float(p.position.y), yaw_of(p.orientation),
                    float(tw.linear.x), float(tw.angular.z))))
            elif topic == TOPIC_STEP:
                m = dec.decode(schema, channel, message)
                k = len(scan.steps)
                if int(m.step) != k:
                    raise BadFile(f"Step message {k} has step = {m.step} (want 0, 1, 2, ... in order)")
                if int(m.episode_id) != scan.info["episode_id"]:
                    raise BadFile(f"step {k}: episode_id {m.episode_id}, EpisodeInfo says "
                                  f"{scan.info['episode_id']}")
                if group[TOPIC_COLOR] != 1 or group[TOPIC_DEPTH] != 1 or pose is None:
                    raise BadFile(f"step {k}: {group[TOPIC_COLOR]} color, {group[TOPIC_DEPTH]} depth, "
                                  f"{0 if pose is None else 1} pose messages before its Step (want 1 each)")
                cont = [float(v) for v in m.action_continuous]
                if len(cont) not in (0, 2):
                    raise BadFile(f"step {k}: action_continuous has {len(cont)} values")
                scan.steps.append(StepInfo(
                    step=k, stamp_ns=stamp_ns(m.header), capture_time_s=stamp_s(m.header),
                    linear_x=float(m.linear_x), angular_z=float(m.angular_z),
                    action_discrete=int(m.action_discrete), action_continuous=cont,
                    reward=float(m.reward), terminated=bool(m.terminated),
                    truncated=bool(m.truncated), success=bool(m.success),
                    end_reason=str(m.end_reason), pose=pose))
                group = {TOPIC_COLOR: 0, TOPIC_DEPTH: 0}
                pose = None
            elif topic == TOPIC_END:
                m = dec.decode(schema, channel, message)
                scan.end = {"steps": int(m.steps), "end_reason": str(m.end_reason),
                            "success": bool(m.success), "terminated": bool(m.terminated),
                            "truncated": bool(m.truncated)}
        if scan is None:
            raise BadFile("no EpisodeInfo (/offworld/episode)")
        if group[TOPIC_COLOR] or group[TOPIC_DEPTH] or pose is not None:
            trailing.append(f"{group[TOPIC_COLOR]} color, {group[TOPIC_DEPTH]} depth, "
                            f"{0 if pose is None else 1} pose after the last Step (ignored)")
        odom.sort(key=lambda t: (t[0], t[1]))  # by stamp; equal stamps keep file order
        scan.odom_stamps = [t for t, _, _ in odom]
        scan.odom_values = [v for _, _, v in odom]
        scan.notes += trailing
        if scan.end is None:
            scan.notes.append("no EpisodeEnd (a recovered file?)")
        elif scan.end["steps"] != len(scan.steps) - 1:
            scan.notes.append(f"EpisodeEnd says {scan.end['steps']} steps, the file has "
                              f"{max(len(scan.steps) - 1, 0)}")
        if scan.end and scan.end["end_reason"].startswith("recorder_stopped"):
            scan.notes.append(f"recording stopped early: {scan.end['end_reason']}")
        return scan


def frames(scan: EpisodeScan):
    """Yields the LeRobot frames (dicts of numpy arrays, without `task`) of one episode."""
    steps = scan.steps
    n = len(steps) - 1
    with open(scan.path, "rb") as f:
        reader = _reader(f)
        dec = _Decoders()
        color = depth = None
        k = 0
        for schema, channel, message in reader.iter_messages(
                topics=[TOPIC_COLOR, TOPIC_DEPTH, TOPIC_STEP], log_time_order=False):
            if k >= n:
                break
            topic = channel.topic
            if topic == TOPIC_COLOR:
                color = color_rgb(dec.decode(schema, channel, message))
            elif topic == TOPIC_DEPTH:
                depth = depth_m(dec.decode(schema, channel, message))
            else:
                s, nxt = steps[k], steps[k + 1]
                if color.shape != scan.color_shape or depth.shape != scan.depth_shape:
                    raise BadFile(f"step {k}: image sizes change within the episode")
                odom = scan.odom_at(s.stamp_ns)
                state = np.array([*s.pose, *odom], dtype=np.float64).astype(np.float32)
                cont = nxt.action_continuous
                yield {
                    "observation.images.color": color,
                    "observation.depth": depth,
                    "observation.state": state,
                    "observation.capture_time_s": np.array([s.capture_time_s], dtype=np.float64),
                    "observation.capture_time_ns": np.array([s.stamp_ns], dtype=np.int64),
                    "action": np.array([nxt.linear_x, nxt.angular_z], dtype=np.float32),
                    "action.discrete": np.array([nxt.action_discrete], dtype=np.int64),
                    "action.normalized": (np.array(cont, dtype=np.float32) if cont
                                          else np.zeros(2, dtype=np.float32)),
                    "next.reward": np.array([nxt.reward], dtype=np.float32),
                    "next.done": np.array([nxt.terminated or nxt.truncated], dtype=bool),
                    "next.truncated": np.array([nxt.truncated], dtype=bool),
                    "next.success": np.array([nxt.success], dtype=bool),
                }
                color = depth = None
                k += 1
    if k != n:
        raise BadFile(f"read {k} frames, expected {n}")


def features_for(color_shape, depth_shape, videos: bool) -> dict:
    h, w, c = color_shape
    return {
        "observation.images.color": {"dtype": "video" if videos else "image",
                                     "shape": (h, w, c), "names": ["height", "width", "channels"]},
        "observation.depth": {"dtype": "float32", "shape": tuple(depth_shape),
                              "names": ["height", "width"]},
        "observation.state": {"dtype": "float32", "shape": (len(STATE_NAMES),), "names": STATE_NAMES},
        "observation.capture_time_s": {"dtype": "float64", "shape": (1,), "names": None},
        "observation.capture_time_ns": {"dtype": "int64", "shape": (1,), "names": None},
        "action": {"dtype": "float32", "shape": (2,), "names": ["linear_x", "angular_z"]},
        "action.discrete": {"dtype": "int64", "shape": (1,), "names": None},
        "action.normalized": {"dtype": "float32", "shape": (2,), "names": ["linear", "angular"]},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
        "next.truncated": {"dtype": "bool", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
    }


# ------------------------------------------------------------- main

def parse_args(argv):
    ap = argparse.ArgumentParser(
        prog="export_lerobot.py",
        description="Export recorded episodes (MCAP) to a LeRobot v3.0 dataset.",
        epilog="Details: the docstring of tools/export_lerobot.py.")
    ap.add_argument("dir", type=Path, help="directory of recordings (searched recursively for *.mcap)")
    ap.add_argument("out", type=Path, help="dataset directory to create (must not exist)")
    ap.add_argument("--repo-id", required=True, help="dataset id, e.g. offworld/monolith-sim")
    ap.add_argument("--fps", type=int, help="frames per second (default: from the median step period)")
    ap.add_argument("--videos", action="store_true",
                    help="store color images as video (lossy) instead of PNG images")
    ap.add_argument("--vcodec", default="libsvtav1",
                    help="video codec with --videos (lerobot's: libsvtav1, h264, hevc, ...)")
    ap.add_argument("--skip-bad", action="store_true",
                    help="skip files that cannot be exported instead of failing")
    return ap.parse_args(argv)


def run(args) -> int:
    t_start = time.monotonic()
    src: Path = args.dir
    out: Path = args.out
    if not src.is_dir():
        raise UsageError(f"{src}: no such directory")
    if out.exists() or out.is_symlink():
        raise UsageError(f"{out} exists; the export creates it (remove it or choose another)")
    if args.fps is not None and args.fps < 1:
        raise UsageError("--fps must be at least 1")
    if args.repo_id.count("/") != 1 or not all(args.repo_id.split("/")):
        raise UsageError(f"--repo-id {args.repo_id!r}: want OWNER/NAME, e.g. offworld/monolith-sim")

    partial = sorted(src.rglob("*.mcap.partial"))
    for p in partial:
        log(f"skip {p.relative_to(src)}: an unfinished episode (.partial); "
            "`recorder recover` makes it a complete file")
    files = sorted(p for p in src.rglob("*.mcap") if p.is_file())
    scans, bad, empty = [], [], []
    for p in files:
        try:
            s = scan_episode(p)
        except Exception as e:  # noqa: BLE001 - any unreadable file is reported the same way
            bad.append((p, f"{type(e).__name__}: {e}" if not isinstance(e, BadFile) else str(e)))
            continue
        if len(s.steps) < 2:
            empty.append(s)
            log(f"skip {p.relative_to(src)}: no step after the reset"
                + ("" if s.steps else " (not even the reset)"))
            continue
        scans.append(s)
    for p, why in bad:
        log(f"{'skip' if args.skip_bad else 'error:'} {p.relative_to(src)}: {why}")
    if bad and not args.skip_bad:
        log(f"{len(bad)} file(s) cannot be exported; nothing written (--skip-bad skips them)")
        return 1
    if not scans:
        raise UsageError(f"no episode to export under {src} ({len(files)} .mcap files, "
                         f"{len(partial)} .partial, {len(empty)} without steps, {len(bad)} bad)")
    scans.sort(key=lambda s: s.key)
    seen = {}
    for s in scans:
        k = s.key[:3]
        if k in seen:
            log(f"warning: {s.path.relative_to(src)} and {seen[k].relative_to(src)} are both "
                f"env {k[0]} experiment {k[1]} episode {k[2]}; both exported")
        seen[k] = s.path

    shapes = {(s.color_shape, s.depth_shape) for s in scans}
    if len(shapes) > 1:
        for s in scans:
            log(f"  {s.path.relative_to(src)}: color {s.color_shape}, depth {s.depth_shape}")
        log("error: image sizes differ between episodes; a LeRobot dataset has one shape per "
            "feature: export them to separate datasets")
        return 1
    color_shape, depth_shape = shapes.pop()
    if args.videos and args.vcodec == "libsvtav1" and color_shape[1] < 32:
        # SVT-AV1 (PyAV 15.1's) dies with SIGFPE on frames 8 or 16 pixels wide (32 works)
        raise UsageError(f"libsvtav1 cannot encode {color_shape[1]}x{color_shape[0]} frames; "
                         "use --vcodec h264")

    if args.fps is not None:
        fps = args.fps
    else:
        periods = [b.stamp_ns - a.stamp_ns for s in scans for a, b in zip(s.steps, s.steps[1:])]
        periods = [p for p in periods if p > 0]
        med = statistics.median(periods) / 1e9 if periods else 1.0
        fps = max(1, round(1.0 / med))
        log(f"fps {fps} (median step period {med * 1000:.1f} ms over {len(periods)} steps)")

    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # the export never needs the Hub
    import warnings

    import datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    datasets.disable_progress_bars()
    # lerobot's stats of bool features (next.done, ...): harmless numpy notice per episode
    warnings.filterwarnings("ignore", message="Converting input from bool", category=RuntimeWarning)

    tmp = out.parent / f"{out.name}.partial-{os.getpid()}"
    features = features_for(color_shape, depth_shape, args.videos)
    total_frames = 0
    sources = []
    try:
        kwargs = {"vcodec": args.vcodec} if args.videos else {}
        ds = LeRobotDataset.create(args.repo_id, fps, features, root=tmp, robot_type=ROBOT_TYPE,
                                   use_videos=args.videos, **kwargs)
        for idx, s in enumerate(scans):
            t0 = time.monotonic()
            task = s.info["task"] or s.info["env_id"]
            n = 0
            for frame in frames(s):
                frame["task"] = task
                ds.add_frame(frame)
                n += 1
            ds.save_episode()
            total_frames += n
            last = s.steps[-1]
            end_reason = s.end["end_reason"] if s.end else last.end_reason
            sources.append({
                "episode_index": idx, "source": str(s.path.relative_to(src)), "frames": n,
                **{k: s.info[k] for k in ("env_id", "experiment_id", "experiment", "episode_id",
                                          "task", "learning_type", "algorithm_mode", "seeded",
                                          "seed", "embodiment", "software_version")},
                "depth_encoding": s.depth_encoding, "end_reason": end_reason,
                "first_capture_time_ns": s.steps[0].stamp_ns,
            })
            log(f"[{idx + 1}/{len(scans)}] {s.info['env_id']} exp {s.info['experiment_id']} "
                f"ep {s.info['episode_id']}: {n} frames, {task!r}, end {end_reason or '-'!r} "
                f"({time.monotonic() - t0:.1f} s) <- {s.path.relative_to(src)}")
            for note in s.notes:
                log(f"    note: {note}")
        ds.finalize()
        images = tmp / "images"  # lerobot's scratch directory for PNGs, left empty
        if images.is_dir() and not any(p.is_file() for p in images.rglob("*")):
            shutil.rmtree(images)
        with open(tmp / "meta" / "offworld_episodes.jsonl", "w") as f:
            for row in sources:
                f.write(json.dumps(row) + "\n")
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise

    log(f"done: {len(scans)} episodes, {total_frames} frames, fps {fps}, "
        f"{'video' if args.videos else 'image'} color, {color_shape[1]}x{color_shape[0]} "
        f"-> {out} (repo id {args.repo_id}) in {time.monotonic() - t_start:.1f} s; "
        f"skipped: {len(partial)} .partial, {len(empty)} without steps"
        + (f", {len(bad)} bad" if bad else ""))
    return 0


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        return run(args)
    except UsageError as e:
        log(f"export_lerobot: {e}")
        return 2
    except BadFile as e:
        log(f"export_lerobot: {e}")
        return 1


if __name__ == "__main__":
    sys.exit(main())
