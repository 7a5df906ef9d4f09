"""A ROS 2 robot on rmw_zenoh, impersonated by independent code.

Uses the Python Zenoh binding (eclipse-zenoh) and the `rosbags` CDR codec,
nothing of ours: it listens for `geometry_msgs/Twist` on the exact rmw_zenoh
key of `/cmd_vel`, and publishes colour (`rgb8`), depth (`16UC1`) and
`nav_msgs/Odometry` on the rmw_zenoh keys of the ROSbot's topics, with the
33-byte rmw_zenoh attachment. Image k carries `frame_id = "frame-<k>"` and
pixel bytes `pattern(k)` so the test can recompute them.

    python3 ros2_robot.py --connect tcp/127.0.0.1:7447

Runs until stdin closes, then prints one JSON object: every Twist received
(decoded by rosbags) with its attachment, and counts.
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import sys
import threading
import time

import numpy as np
import zenoh
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types

HASH = {
    "geometry_msgs/msg/Twist": "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a",
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "nav_msgs/msg/Odometry": "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
}
WIDTH, HEIGHT = 8, 6


def rmw_key(domain: int, topic: str, ros_type: str) -> str:
    pkg, _, name = ros_type.split("/")
    return f"{domain}/{topic}/{pkg}::msg::dds_::{name}_/{HASH[ros_type]}"


def color_pattern(k: int) -> bytes:
    return bytes((i * 7 + k) % 256 for i in range(WIDTH * HEIGHT * 3))


def depth_pattern(k: int) -> bytes:
    return np.array([1000 + k + i for i in range(WIDTH * HEIGHT)], dtype="<u2").tobytes()


class Robot:
    def __init__(self, session: zenoh.Session, domain: int) -> None:
        self.session = session
        self.domain = domain
        self.gid = os.urandom(16)
        self.seq = 0
        self.twists: list[dict] = []
        self.bad_twists = 0
        self.lock = threading.Lock()

    def attachment(self) -> bytes:
        self.seq += 1
        return struct.pack("<qqB", self.seq, time.time_ns(), 16) + self.gid

    def on_twist(self, sample: zenoh.Sample) -> None:
        raw = sample.payload.to_bytes()
        att = sample.attachment.to_bytes() if sample.attachment is not None else b""
        try:
            msg = TS.deserialize_cdr(raw, "geometry_msgs/msg/Twist")
        except Exception:  # noqa: BLE001 - count anything rosbags rejects
            with self.lock:
                self.bad_twists += 1
            return
        entry = {
            "linear": [msg.linear.x, msg.linear.y, msg.linear.z],
            "angular": [msg.angular.x, msg.angular.y, msg.angular.z],
            "bytes": len(raw),
            "attachment_len": len(att),
        }
        if len(att) == 33:
            seq, stamp, gid_len = struct.unpack("<qqB", att[:17])
            entry.update(seq=seq, stamp_ns=stamp, gid_len=gid_len, gid=att[17:].hex())
        with self.lock:
            self.twists.append(entry)

    def header(self, k: int):
        now = time.time_ns()
        stamp = T["builtin_interfaces/msg/Time"](sec=now // 1_000_000_000, nanosec=now % 1_000_000_000)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=f"frame-{k}")

    def image(self, k: int, encoding: str, step: int, data: bytes):
        return T["sensor_msgs/msg/Image"](
            header=self.header(k),
            height=HEIGHT,
            width=WIDTH,
            encoding=encoding,
            is_bigendian=0,
            step=step,
            data=np.frombuffer(data, dtype=np.uint8),
        )

    def odometry(self, k: int):
        point = T["geometry_msgs/msg/Point"](x=0.01 * k, y=0.0, z=0.0)
        quat = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
        pose = T["geometry_msgs/msg/Pose"](position=point, orientation=quat)
        vec = T["geometry_msgs/msg/Vector3"]
        twist = T["geometry_msgs/msg/Twist"](linear=vec(x=0.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0))
        cov = np.zeros(36, dtype=np.float64)
        return T["nav_msgs/msg/Odometry"](
            header=self.header(k),
            child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov),
        )

    def publish(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload, attachment=self.attachment())

    def stream(self, stop: threading.Event) -> int:
        color = rmw_key(self.domain, "camera/color/image_raw", "sensor_msgs/msg/Image")
        depth = rmw_key(self.domain, "camera/depth/image_raw", "sensor_msgs/msg/Image")
        odom = rmw_key(self.domain, "odom", "nav_msgs/msg/Odometry")
        # A garbled frame first: the agent must reject it and keep serving.
        self.publish(color, b"\x00\x01\x00\x00garbage")
        k = 0
        while not stop.is_set():
            k += 1
            img = self.image(k, "rgb8", WIDTH * 3, color_pattern(k))
            self.publish(color, bytes(TS.serialize_cdr(img, "sensor_msgs/msg/Image")))
            img = self.image(k, "16UC1", WIDTH * 2, depth_pattern(k))
            self.publish(depth, bytes(TS.serialize_cdr(img, "sensor_msgs/msg/Image")))
            self.publish(odom, bytes(TS.serialize_cdr(self.odometry(k), "nav_msgs/msg/Odometry")))
            time.sleep(0.03)
        return k


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--connect", required=True)
    parser.add_argument("--domain", type=int, default=0)
    args = parser.parse_args()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    robot = Robot(session, args.domain)
    sub = session.declare_subscriber(rmw_key(args.domain, "cmd_vel", "geometry_msgs/msg/Twist"), robot.on_twist)
    stop = threading.Event()
    published = [0]
    streamer = threading.Thread(target=lambda: published.__setitem__(0, robot.stream(stop)), daemon=True)
    streamer.start()
    print("ready", file=sys.stderr, flush=True)
    sys.stdin.read()  # until the test closes stdin
    stop.set()
    streamer.join(timeout=5)
    sub.undeclare()
    with robot.lock:
        report = {"twists": robot.twists, "bad_twists": robot.bad_twists, "frames": published[0]}
    session.close()
    print(json.dumps(report), flush=True)


if __name__ == "__main__":
    main()
