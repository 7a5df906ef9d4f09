#!/usr/bin/env python3
"""Write a few small episode recordings in the format of docs/recording.md.

    python tests/lerobot/make_sample_episodes.py OUTDIR

Needs `mcap` and `mcap-ros2-support` (the LeRobot venv has them:
`"$(tools/lerobot-venv)" tests/lerobot/make_sample_episodes.py OUTDIR`). OUTDIR must
not exist. It gets, in the documented layout
`OUTDIR/<realm>/<env name>/exp-<experiment id>/ep-<episode id>.mcap`:

- `real/enclosure-a/exp-000004/ep-000007.mcap`: MonolithContinuous, 4 steps,
  depth `16UC1` (mm, 0 = no return), continuous actions, ends aborted
  (neither terminated nor truncated).
- `sim/monolith-0/exp-000003/ep-000001.mcap`: MonolithDiscrete, 5 steps, depth
  `32FC1` with NaN (no return), ends in success (terminated).
- `sim/monolith-0/exp-000003/ep-000002.mcap`: MonolithDiscrete, 3 steps, ends
  truncated (max_episode_steps = 3).
- `sim/monolith-0/exp-000003/ep-000003.mcap`: only the reset (0 steps): an
  exporter skips it.
- `sim/monolith-0/exp-000003/ep-000004.mcap.partial`: an episode cut off in the
  middle (a finished file truncated inside its data): an exporter skips it.

Images are 8x6 (width x height). Odometry comes three times per step period,
the first one after the reset frame (so step 0 has no odometry at or before
its capture time) and one exactly at a capture time (the "at or before" edge).
Everything is deterministic (fixed times and seeds).

This exists so that tools/export_lerobot.py and its test can be developed
before the Rust recorder writes real files; it is written from the spec, not
from the recorder's code. The schemas are the `.msg` files in recorder/msg
joined by the rosbag2 rule (see `full_text`).
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer

MSG_DIR = Path(__file__).resolve().parents[2] / "recorder" / "msg"

PRIMITIVES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string", "wstring",
}
_DEP_RE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")

# offered_qos_profiles as rosbag2 writes it in the numeric (bag version 8) form
# (docs/design/datasets.md section 2): keep_last 10, reliable, volatile, automatic.
_NEVER = "    sec: 9223372036\n    nsec: 854775807\n"
QOS = (
    "- history: 1\n  depth: 10\n  reliability: 1\n  durability: 2\n"
    f"  deadline:\n{_NEVER}  lifespan:\n{_NEVER}  liveliness: 1\n"
    f"  liveliness_lease_duration:\n{_NEVER}  avoid_ros_namespace_conventions: false"
)

TOPICS = {
    "/offworld/episode": "offworld_msgs/msg/EpisodeInfo",
    "/camera/color/image_raw": "sensor_msgs/msg/Image",
    "/camera/depth/image_raw": "sensor_msgs/msg/Image",
    "/tracker/pose": "geometry_msgs/msg/PoseStamped",
    "/odom": "nav_msgs/msg/Odometry",
    "/cmd_vel": "geometry_msgs/msg/Twist",
    "/offworld/step": "offworld_msgs/msg/Step",
    "/offworld/episode_end": "offworld_msgs/msg/EpisodeEnd",
}

WIDTH, HEIGHT = 8, 6
# Discrete action table of the samples (index -> linear m/s, angular rad/s).
DISCRETE = [(0.2, 0.0), (0.0, 0.6), (0.0, -0.6), (-0.2, 0.0)]
MAX_LINEAR, MAX_ANGULAR = 0.3, 1.0


def _msg_text(pkg_type: str) -> str:
    """`pkg/Type` or `pkg/msg/Type` -> the .msg file text."""
    pkg, _, name = pkg_type.replace("/msg/", "/").partition("/")
    return (MSG_DIR / pkg / "msg" / f"{name}.msg").read_text()


def _deps(pkg: str, text: str) -> list[str]:
    out = set()
    for word in _DEP_RE.findall(text):
        if word in PRIMITIVES:
            continue
        out.add(word if "/" in word else f"{pkg}/{word}")
    return sorted(out)


def full_text(datatype: str) -> str:
    """The ros2msg schema text of `pkg/msg/Type`, joined as rosbag2 does
    (LocalMessageDefinitionSource::get_full_text): the root file, then each
    dependency `pkg/Type` depth-first in sorted order, each once, as
    "\\n" + "=" * 80 + "\\nMSG: pkg/Type\\n" + its text."""
    seen: set[str] = set()

    def rec(pkg_type: str) -> str:
        pkg = pkg_type.split("/")[0]
        text = _msg_text(pkg_type)
        for dep in _deps(pkg, text):
            if dep not in seen:
                seen.add(dep)
                text += "\n" + "=" * 80 + "\nMSG: " + dep + "\n" + rec(dep)
        return text

    return rec(datatype)


# ---------------------------------------------------------------- messages

def _stamp(t_ns: int) -> dict:
    return {"sec": t_ns // 1_000_000_000, "nanosec": t_ns % 1_000_000_000}


def _header(t_ns: int, frame_id: str) -> dict:
    return {"stamp": _stamp(t_ns), "frame_id": frame_id}


def _quat(yaw: float) -> dict:
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}


def _image(t_ns: int, frame_id: str, encoding: str, arr: np.ndarray) -> dict:
    h, w = arr.shape[:2]
    data = np.ascontiguousarray(arr).tobytes()
    return {
        "header": _header(t_ns, frame_id), "height": h, "width": w, "encoding": encoding,
        "is_bigendian": 0, "step": len(data) // h, "data": data,
    }


@dataclass
class EpisodeSpec:
    rel_path: str
    env_id: str
    task: str
    world: str
    experiment_id: int
    experiment: str
    learning_type: str
    episode_id: int
    seed: int
    embodiment: str
    max_episode_steps: int
    discrete: bool
    depth_encoding: str  # 32FC1 | 16UC1
    steps: int
    start_ns: int
    period_ns: int
    end: str  # success | timeout | aborted
    jitter_ns: list[int] = field(default_factory=list)


def _write_episode(path: Path, ep: EpisodeSpec) -> None:
    rng = np.random.default_rng(ep.seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=64 * 1024, compression=CompressionType.ZSTD)
        schemas = {}
        for topic, datatype in TOPICS.items():
            if datatype not in schemas:
                schemas[datatype] = w.register_msgdef(datatype, full_text(datatype))
            # Register the channel ourselves to carry rosbag2's channel metadata
            # (mcap_ros2's Writer registers channels without metadata).
            cid = w._writer.register_channel(  # noqa: SLF001 - no public API for it
                topic=topic, message_encoding="cdr", schema_id=schemas[datatype].id,
                metadata={"offered_qos_profiles": QOS},
            )
            w._channel_ids[topic] = cid  # noqa: SLF001

        seqs = {t: 0 for t in TOPICS}

        def put(topic: str, msg: dict, log_ns: int, recv_delay_ns: int = 2_000_000) -> None:
            w.write_message(topic, schemas[TOPICS[topic]], msg, log_time=log_ns,
                            publish_time=log_ns + recv_delay_ns, sequence=seqs[topic])
            seqs[topic] += 1

        info = {
            "env_id": ep.env_id, "task": ep.task, "world": ep.world,
            "experiment_id": ep.experiment_id, "experiment": ep.experiment,
            "learning_type": ep.learning_type, "algorithm_mode": "train",
            "episode_id": ep.episode_id, "seeded": True, "seed": ep.seed,
            "embodiment": ep.embodiment, "software_version": "offworld-recorder/0.0.0-sample",
            "max_episode_steps": ep.max_episode_steps,
            "requested_start": [0.5, -0.25, 0.1],
        }
        put("/offworld/episode", {"header": _header(ep.start_ns, "world"), **info}, ep.start_ns)
        w.add_metadata("offworld.episode", {
            k: (",".join(repr(x) for x in v) if isinstance(v, list)
                else ("true" if v is True else "false" if v is False else str(v)))
            for k, v in info.items()
        })

        # capture times of s0..sN
        t0 = ep.start_ns + 150_000_000
        times = [t0 + k * ep.period_ns + (ep.jitter_ns[k] if k < len(ep.jitter_ns) else 0)
                 for k in range(ep.steps + 1)]
        x, y, yaw = 0.5, -0.25, 0.1
        odom_x = odom_y = odom_yaw = 0.0
        episode_return = 0.0
        for k, t in enumerate(times):
            if k > 0:
                # the command of step k, sent right after step k-1 answered
                if ep.discrete:
                    a = int(rng.integers(0, len(DISCRETE)))
                    lin, ang = DISCRETE[a]
                    cont: list[float] = []
                else:
                    a = -1
                    cont = [float(np.float32(v)) for v in rng.uniform(-1, 1, 2).round(3)]
                    lin, ang = cont[0] * MAX_LINEAR, cont[1] * MAX_ANGULAR
                duration = 0.2
                sent = times[k - 1] + 5_000_000
                put("/cmd_vel", {"linear": {"x": lin, "y": 0.0, "z": 0.0},
                                 "angular": {"x": 0.0, "y": 0.0, "z": ang}}, sent)
                # odometry while it moves: 3 messages per period; the last one
                # of step 2 exactly at the capture time
                for frac in (0.3, 0.6, 1.0 if k == 2 else 0.9):
                    to = times[k - 1] + int((t - times[k - 1]) * frac)
                    odom_x += lin * duration / 3 * math.cos(odom_yaw)
                    odom_y += lin * duration / 3 * math.sin(odom_yaw)
                    odom_yaw += ang * duration / 3
                    put("/odom", {
                        "header": _header(to, "odom"), "child_frame_id": "base_link",
                        "pose": {"pose": {"position": {"x": odom_x, "y": odom_y, "z": 0.0},
                                          "orientation": _quat(odom_yaw)},
                                 "covariance": [0.0] * 36},
                        "twist": {"twist": {"linear": {"x": lin, "y": 0.0, "z": 0.0},
                                            "angular": {"x": 0.0, "y": 0.0, "z": ang}},
                                  "covariance": [0.0] * 36},
                    }, to)
                x += lin * duration * math.cos(yaw) + float(rng.normal(0, 0.002))
                y += lin * duration * math.sin(yaw) + float(rng.normal(0, 0.002))
                yaw += ang * duration
            else:
                a, cont, lin, ang, duration = -1, [], 0.0, 0.0, 0.0

            color = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
            color[0, 0] = (k * 10 % 256, 0, 255)  # frame marker
            put("/camera/color/image_raw", _image(t, "camera_color_optical_frame", "rgb8", color), t)
            if ep.depth_encoding == "32FC1":
                depth = rng.uniform(0.3, 4.0, (HEIGHT, WIDTH)).astype(np.float32)
                depth[rng.random((HEIGHT, WIDTH)) < 0.15] = np.nan
                depth[1, 2] = np.nan
            else:
                depth = rng.integers(300, 4000, (HEIGHT, WIDTH), dtype=np.uint16)
                depth[rng.random((HEIGHT, WIDTH)) < 0.15] = 0
                depth[1, 2] = 0
            put("/camera/depth/image_raw",
                _image(t, "camera_depth_optical_frame", ep.depth_encoding, depth), t)
            pose_t = t - 7_000_000
            put("/tracker/pose", {"header": _header(pose_t, "world"),
                                  "pose": {"position": {"x": x, "y": y, "z": 0.0},
                                           "orientation": _quat(yaw)}}, pose_t)

            last = k == ep.steps and k > 0
            terminated = last and ep.end == "success"
            truncated = last and ep.end == "timeout"
            success = terminated
            reward = 0.0 if k == 0 else (10.0 if success else round(float(rng.normal(-0.1, 0.05)), 4))
            episode_return += reward
            end_reason = ""
            if last:
                end_reason = {"success": "success", "timeout": "timeout",
                              "aborted": "aborted: lease expired"}[ep.end]
            put("/offworld/step", {
                "header": _header(t, "world"), "episode_id": ep.episode_id, "step": k,
                "command_seq": 1000 + k, "action_discrete": a, "action_continuous": cont,
                "linear_x": lin, "angular_z": ang, "duration_s": duration,
                "reward": reward, "episode_return": episode_return,
                "terminated": terminated, "truncated": truncated, "success": success,
                "end_reason": end_reason,
            }, t)
        end_t = times[-1] + 10_000_000
        if ep.steps == 0:
            end_reason, success, terminated, truncated = "aborted: closed", False, False, False
        put("/offworld/episode_end", {
            "header": _header(end_t, "world"), "episode_id": ep.episode_id, "steps": ep.steps,
            "episode_return": episode_return, "success": success, "terminated": terminated,
            "truncated": truncated, "end_reason": end_reason,
        }, end_t)
        w.finish()


SAMPLES = [
    EpisodeSpec("real/enclosure-a/exp-000004/ep-000007.mcap", "real/enclosure-a",
                "MonolithContinuous: reach the monolith", "monolith", 4, "cont-demo",
                "humandemos", 7, 44, "robot", 100, False, "16UC1", 4,
                1_750_000_500_000_000_000, 250_000_000, "aborted",
                [0, 3_000_000, -2_000_000, 1_000_000, 4_000_000]),
    EpisodeSpec("sim/monolith-0/exp-000003/ep-000001.mcap", "sim/monolith-0",
                "MonolithDiscrete: reach the monolith", "monolith", 3, "disc-train",
                "end2end", 1, 11, "twin", 100, True, "32FC1", 5,
                1_750_000_000_000_000_000, 250_000_000, "success"),
    EpisodeSpec("sim/monolith-0/exp-000003/ep-000002.mcap", "sim/monolith-0",
                "MonolithDiscrete: reach the monolith", "monolith", 3, "disc-train",
                "end2end", 2, 12, "twin", 3, True, "32FC1", 3,
                1_750_000_010_000_000_000, 250_000_000, "timeout"),
    EpisodeSpec("sim/monolith-0/exp-000003/ep-000003.mcap", "sim/monolith-0",
                "MonolithDiscrete: reach the monolith", "monolith", 3, "disc-train",
                "end2end", 3, 13, "twin", 100, True, "32FC1", 0,
                1_750_000_020_000_000_000, 250_000_000, "aborted"),
]


def make_samples(outdir: Path) -> list[Path]:
    """Writes the samples into `outdir` (must not exist); returns the complete files."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=False)
    paths = []
    for ep in SAMPLES:
        p = outdir / ep.rel_path
        _write_episode(p, ep)
        paths.append(p)
    # a crashed episode: a finished file cut inside its data, renamed .partial
    cut = EpisodeSpec("sim/monolith-0/exp-000003/ep-000004.mcap", "sim/monolith-0",
                      "MonolithDiscrete: reach the monolith", "monolith", 3, "disc-train",
                      "end2end", 4, 14, "twin", 100, True, "32FC1", 4,
                      1_750_000_030_000_000_000, 250_000_000, "success")
    full = outdir / (cut.rel_path + ".tmp")
    _write_episode(full, cut)
    data = full.read_bytes()
    (outdir / (cut.rel_path + ".partial")).write_bytes(data[: len(data) * 2 // 3])
    full.unlink()
    return paths


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("outdir", type=Path)
    args = ap.parse_args(argv)
    if args.outdir.exists():
        print(f"make_sample_episodes: {args.outdir} exists", file=sys.stderr)
        return 2
    for p in make_samples(args.outdir):
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
