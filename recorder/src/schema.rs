//! Message schemas as rosbag2 writes them into MCAP (`ros2msg`): a type's
//! `.msg` text followed by the text of every type it depends on.

use std::collections::BTreeSet;

/// The `.msg` files of every type a recording holds (field definitions;
/// decoders and type hashes ignore comments), by `pkg/msg/Type`.
const MSG_FILES: &[(&str, &str)] = &[
    (
        "builtin_interfaces/msg/Time",
        include_str!("../msg/builtin_interfaces/msg/Time.msg"),
    ),
    (
        "std_msgs/msg/Header",
        include_str!("../msg/std_msgs/msg/Header.msg"),
    ),
    (
        "geometry_msgs/msg/Point",
        include_str!("../msg/geometry_msgs/msg/Point.msg"),
    ),
    (
        "geometry_msgs/msg/Quaternion",
        include_str!("../msg/geometry_msgs/msg/Quaternion.msg"),
    ),
    (
        "geometry_msgs/msg/Pose",
        include_str!("../msg/geometry_msgs/msg/Pose.msg"),
    ),
    (
        "geometry_msgs/msg/PoseStamped",
        include_str!("../msg/geometry_msgs/msg/PoseStamped.msg"),
    ),
    (
        "geometry_msgs/msg/PoseWithCovariance",
        include_str!("../msg/geometry_msgs/msg/PoseWithCovariance.msg"),
    ),
    (
        "geometry_msgs/msg/Vector3",
        include_str!("../msg/geometry_msgs/msg/Vector3.msg"),
    ),
    (
        "geometry_msgs/msg/Twist",
        include_str!("../msg/geometry_msgs/msg/Twist.msg"),
    ),
    (
        "geometry_msgs/msg/TwistWithCovariance",
        include_str!("../msg/geometry_msgs/msg/TwistWithCovariance.msg"),
    ),
    (
        "nav_msgs/msg/Odometry",
        include_str!("../msg/nav_msgs/msg/Odometry.msg"),
    ),
    (
        "sensor_msgs/msg/Image",
        include_str!("../msg/sensor_msgs/msg/Image.msg"),
    ),
    (
        "offworld_msgs/msg/Step",
        include_str!("../msg/offworld_msgs/msg/Step.msg"),
    ),
    (
        "offworld_msgs/msg/EpisodeInfo",
        include_str!("../msg/offworld_msgs/msg/EpisodeInfo.msg"),
    ),
    (
        "offworld_msgs/msg/EpisodeEnd",
        include_str!("../msg/offworld_msgs/msg/EpisodeEnd.msg"),
    ),
];

/// ROS primitive field types (no dependency).
const PRIMITIVES: &[&str] = &[
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
];

/// The `.msg` text of `pkg/msg/Type`, if it is one of ours.
pub fn msg_text(type_name: &str) -> Option<&'static str> {
    MSG_FILES
        .iter()
        .find(|(name, _)| *name == type_name)
        .map(|(_, text)| *text)
}

/// The types `text` (of package `pkg`) refers to, as `pkg/Type`, sorted
/// (rosbag2 keeps them in a `std::set`).
fn dependencies(pkg: &str, text: &str) -> BTreeSet<String> {
    text.lines()
        .map(|line| line.split('#').next().unwrap_or_default().trim())
        .filter(|line| !line.is_empty())
        .filter_map(|line| line.split_whitespace().next())
        // Constants are `type NAME=value`; arrays `type[N]` or `type[]`;
        // bounded strings `string<=N`.
        .map(|ty| ty.split(['[', '<']).next().unwrap_or(ty))
        .filter(|ty| !PRIMITIVES.contains(ty))
        .map(|ty| {
            if ty.contains('/') {
                ty.to_owned()
            } else {
                format!("{pkg}/{ty}")
            }
        })
        .collect()
}

/// The schema data rosbag2 stores for `type_name` (`pkg/msg/Type`): its
/// text, then for each dependency not yet written (sorted, depth first) a
/// line of 80 `=`, `MSG: pkg/Type` and that type's text. `None` for a type
/// this crate does not know.
pub fn full_text(type_name: &str) -> Option<String> {
    let mut seen = BTreeSet::new();
    append(type_name, &mut seen)
}

fn append(type_name: &str, seen: &mut BTreeSet<String>) -> Option<String> {
    let text = msg_text(type_name)?;
    let pkg = type_name.split('/').next()?;
    let mut out = text.to_owned();
    for dep in dependencies(pkg, text) {
        if seen.insert(dep.clone()) {
            let (dep_pkg, dep_type) = dep.split_once('/')?;
            out.push('\n');
            out.push_str(&"=".repeat(80));
            out.push_str("\nMSG: ");
            out.push_str(&dep);
            out.push('\n');
            out.push_str(&append(&format!("{dep_pkg}/msg/{dep_type}"), seen)?);
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_type_and_dependency_is_known() {
        for (name, _) in MSG_FILES {
            let text =
                full_text(name).unwrap_or_else(|| panic!("{name} has an unknown dependency"));
            assert!(text.starts_with(msg_text(name).expect("known")));
        }
        assert_eq!(full_text("nope/msg/Nope"), None);
    }

    #[test]
    fn dependencies_follow_the_rosbag2_rule() {
        // Sorted, depth first, each once: the order rosbag2 writes.
        let text = full_text("nav_msgs/msg/Odometry").expect("odometry");
        let order: Vec<&str> = text
            .lines()
            .filter_map(|l| l.strip_prefix("MSG: "))
            .collect();
        assert_eq!(
            order,
            [
                "geometry_msgs/PoseWithCovariance",
                "geometry_msgs/Pose",
                "geometry_msgs/Point",
                "geometry_msgs/Quaternion",
                "geometry_msgs/TwistWithCovariance",
                "geometry_msgs/Twist",
                "geometry_msgs/Vector3",
                "std_msgs/Header",
                "builtin_interfaces/Time",
            ]
        );
        let image = full_text("sensor_msgs/msg/Image").expect("image");
        assert_eq!(
            image,
            format!(
                "{}\n{sep}\nMSG: std_msgs/Header\n{}\n{sep}\nMSG: builtin_interfaces/Time\n{}",
                msg_text("sensor_msgs/msg/Image").expect("image"),
                msg_text("std_msgs/msg/Header").expect("header"),
                msg_text("builtin_interfaces/msg/Time").expect("time"),
                sep = "=".repeat(80)
            )
        );
    }
}
