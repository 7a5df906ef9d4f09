"""Independent CDR reference: encodes ROS 2 messages with `rosbags`.

Reads JSON lines `{"type": "...", "msg": {...}}` on stdin and prints, for
each, the rosbags CDR bytes as hex. Used by runtime/tests/integration/rosbags_golden.rs
to prove our encoder is byte-identical to a codec we did not write.
"""

import json
import sys

import numpy as np
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types


def time(d):
    return T["builtin_interfaces/msg/Time"](sec=d["sec"], nanosec=d["nanosec"])


def header(d):
    return T["std_msgs/msg/Header"](stamp=time(d["stamp"]), frame_id=d["frame_id"])


def vec3(d, kind="geometry_msgs/msg/Vector3"):
    return T[kind](x=d["x"], y=d["y"], z=d["z"])


def quat(d):
    return T["geometry_msgs/msg/Quaternion"](x=d["x"], y=d["y"], z=d["z"], w=d["w"])


def pose(d):
    return T["geometry_msgs/msg/Pose"](
        position=vec3(d["position"], "geometry_msgs/msg/Point"), orientation=quat(d["orientation"])
    )


def twist(d):
    return T["geometry_msgs/msg/Twist"](linear=vec3(d["linear"]), angular=vec3(d["angular"]))


BUILD = {
    "geometry_msgs/msg/Twist": twist,
    "geometry_msgs/msg/PoseStamped": lambda d: T["geometry_msgs/msg/PoseStamped"](
        header=header(d["header"]), pose=pose(d["pose"])
    ),
    "nav_msgs/msg/Odometry": lambda d: T["nav_msgs/msg/Odometry"](
        header=header(d["header"]),
        child_frame_id=d["child_frame_id"],
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=pose(d["pose"]["pose"]), covariance=np.array(d["pose"]["covariance"], dtype=np.float64)
        ),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=twist(d["twist"]["twist"]),
            covariance=np.array(d["twist"]["covariance"], dtype=np.float64),
        ),
    ),
    "sensor_msgs/msg/Image": lambda d: T["sensor_msgs/msg/Image"](
        header=header(d["header"]),
        height=d["height"],
        width=d["width"],
        encoding=d["encoding"],
        is_bigendian=d["is_bigendian"],
        step=d["step"],
        data=np.array(d["data"], dtype=np.uint8),
    ),
}


def main():
    for line in sys.stdin:
        if not line.strip():
            continue
        req = json.loads(line)
        msg = BUILD[req["type"]](req["msg"])
        print(bytes(TS.serialize_cdr(msg, req["type"])).hex(), flush=True)


if __name__ == "__main__":
    main()
