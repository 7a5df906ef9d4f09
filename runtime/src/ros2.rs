//! Talking to a ROS 2 robot over Zenoh without a ROS install: the key
//! expressions of its topics and rmw_zenoh's per-publication attachment.
//!
//! Two key styles exist in the field:
//! - [`KeyStyle::RmwZenoh`] (ROS 2 with `rmw_zenoh`):
//!   `<domain_id>/<fully qualified topic>/<dds type name>/<type hash>`;
//! - [`KeyStyle::Bridge`] (`zenoh-bridge-ros2dds`): `[<prefix>/]<topic>`.
//!
//! Payloads are the CDR bytes of [`crate::msg`]'s ROS types either way.

use std::fmt;
use std::sync::atomic::{AtomicI64, Ordering};

use serde::{Deserialize, Serialize};

use crate::error::{ContractError, DecodeError};

/// The ROS 2 message types the robot side exchanges.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RosType {
    /// `geometry_msgs/msg/Twist`.
    Twist,
    /// `sensor_msgs/msg/Image`.
    Image,
    /// `nav_msgs/msg/Odometry`.
    Odometry,
    /// `geometry_msgs/msg/PoseStamped`.
    PoseStamped,
}

impl RosType {
    /// The ROS interface name, e.g. `geometry_msgs/msg/Twist`.
    pub fn ros_name(self) -> &'static str {
        match self {
            RosType::Twist => "geometry_msgs/msg/Twist",
            RosType::Image => "sensor_msgs/msg/Image",
            RosType::Odometry => "nav_msgs/msg/Odometry",
            RosType::PoseStamped => "geometry_msgs/msg/PoseStamped",
        }
    }

    /// The DDS type name rmw_zenoh puts in keys.
    pub fn dds_name(self) -> &'static str {
        match self {
            RosType::Twist => "geometry_msgs::msg::dds_::Twist_",
            RosType::Image => "sensor_msgs::msg::dds_::Image_",
            RosType::Odometry => "nav_msgs::msg::dds_::Odometry_",
            RosType::PoseStamped => "geometry_msgs::msg::dds_::PoseStamped_",
        }
    }

    /// The REP-2016 type hash (ROS 2 Iron and later).
    pub fn type_hash(self) -> &'static str {
        match self {
            RosType::Twist => {
                "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
            }
            RosType::Image => {
                "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
            }
            RosType::Odometry => {
                "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
            }
            RosType::PoseStamped => {
                "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
            }
        }
    }
}

/// How the robot's ROS 2 graph appears in Zenoh.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "style", rename_all = "snake_case", deny_unknown_fields)]
pub enum KeyStyle {
    /// ROS 2 running `rmw_zenoh`.
    RmwZenoh {
        /// `ROS_DOMAIN_ID`.
        domain_id: u32,
    },
    /// `zenoh-bridge-ros2dds` in front of a DDS robot.
    Bridge {
        /// The bridge's `namespace` option, if set.
        #[serde(default)]
        prefix: Option<String>,
    },
}

impl Default for KeyStyle {
    fn default() -> Self {
        KeyStyle::RmwZenoh { domain_id: 0 }
    }
}

/// One robot's ROS 2 graph: key style plus the robot's namespace.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RosGraph {
    style: KeyStyle,
    namespace: String,
}

impl RosGraph {
    /// `namespace` like `/rosbot` or empty for the root namespace.
    /// A bridge prefix is kept normalised (`/site_a` → `site_a`): the
    /// bridge's `namespace` option is written either way, and a leading
    /// `/` would not be a Zenoh key expression.
    pub fn new(style: KeyStyle, namespace: &str) -> Result<Self, ContractError> {
        let namespace = normalize_name(namespace, true)?;
        let style = match style {
            KeyStyle::Bridge {
                prefix: Some(prefix),
            } => KeyStyle::Bridge {
                prefix: Some(normalize_name(&prefix, false)?),
            },
            other => other,
        };
        Ok(Self { style, namespace })
    }

    /// The key style.
    pub fn style(&self) -> &KeyStyle {
        &self.style
    }

    /// The fully qualified topic name without its leading `/`: relative
    /// names live in the robot's namespace, absolute ones (`/odom`) do not.
    pub fn qualify(&self, topic: &str) -> Result<String, ContractError> {
        let absolute = topic.starts_with('/');
        let name = normalize_name(topic, false)?;
        Ok(if absolute || self.namespace.is_empty() {
            name
        } else {
            format!("{}/{name}", self.namespace)
        })
    }

    /// The exact key a ROS publisher of `topic` uses.
    pub fn publication_key(&self, topic: &str, ty: RosType) -> Result<String, ContractError> {
        self.key(topic, ty, ty.type_hash())
    }

    /// A key expression matching every publisher of `topic`: rmw_zenoh's
    /// type hash is wildcarded because distributions before Iron publish
    /// `TypeHashNotSupported` there.
    pub fn subscription_key(&self, topic: &str, ty: RosType) -> Result<String, ContractError> {
        self.key(topic, ty, "*")
    }

    fn key(&self, topic: &str, ty: RosType, hash: &str) -> Result<String, ContractError> {
        let name = self.qualify(topic)?;
        Ok(match &self.style {
            KeyStyle::RmwZenoh { domain_id } => {
                format!("{domain_id}/{name}/{}/{hash}", ty.dds_name())
            }
            KeyStyle::Bridge { prefix: Some(p) } => format!("{p}/{name}"),
            KeyStyle::Bridge { prefix: None } => name,
        })
    }
}

impl fmt::Display for RosGraph {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.style {
            KeyStyle::RmwZenoh { domain_id } => {
                write!(f, "rmw_zenoh domain {domain_id} /{}", self.namespace)
            }
            KeyStyle::Bridge { prefix } => write!(
                f,
                "zenoh-bridge-ros2dds {}/{}",
                prefix.as_deref().unwrap_or(""),
                self.namespace
            ),
        }
    }
}

/// A ROS name (`/a/b_c`) without its leading `/`; rejects what ROS rejects
/// and anything that would be a Zenoh wildcard or verbatim chunk.
fn normalize_name(name: &str, allow_empty: bool) -> Result<String, ContractError> {
    let trimmed = name.strip_prefix('/').unwrap_or(name);
    let bad = |why: &str| Err(ContractError::InvalidRosName(format!("`{name}`: {why}")));
    if trimmed.is_empty() {
        return if allow_empty {
            Ok(String::new())
        } else {
            bad("empty")
        };
    }
    for token in trimmed.split('/') {
        if token.is_empty() {
            return bad("empty token (`//` or trailing `/`)");
        }
        if token.as_bytes()[0].is_ascii_digit() {
            return bad("a token starts with a digit");
        }
        if !token
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_')
        {
            return bad("only [A-Za-z0-9_] and `/` are allowed");
        }
    }
    Ok(trimmed.to_owned())
}

/// The robot's ROS 2 topic names (relative names live in its namespace).
/// Defaults are a ROSbot 2 with an Orbbec Astra driver.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RobotTopics {
    /// `geometry_msgs/Twist` velocity commands to the base.
    pub cmd_vel: String,
    /// `sensor_msgs/Image` colour (`rgb8` or `bgr8`).
    pub color: String,
    /// `sensor_msgs/Image` depth (`16UC1` mm or `32FC1` m).
    pub depth: String,
    /// `nav_msgs/Odometry` wheel odometry.
    pub odom: String,
}

impl Default for RobotTopics {
    fn default() -> Self {
        Self {
            cmd_vel: "cmd_vel".into(),
            color: "camera/color/image_raw".into(),
            depth: "camera/depth/image_raw".into(),
            odom: "odom".into(),
        }
    }
}

/// Length of rmw_zenoh's attachment.
pub const RMW_ATTACHMENT_LEN: usize = 33;

/// What rmw_zenoh attaches to every publication: sequence number, source
/// timestamp and the publisher's GID.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RmwAttachment {
    /// Per-publisher sequence number.
    pub sequence: i64,
    /// Source timestamp, ns since the Unix epoch.
    pub source_timestamp_ns: i64,
    /// Publisher GID.
    pub gid: [u8; 16],
}

impl RmwAttachment {
    /// The 33 wire bytes: i64 LE, i64 LE, u8 length (16), GID.
    pub fn to_bytes(&self) -> [u8; RMW_ATTACHMENT_LEN] {
        let mut out = [0u8; RMW_ATTACHMENT_LEN];
        out[..8].copy_from_slice(&self.sequence.to_le_bytes());
        out[8..16].copy_from_slice(&self.source_timestamp_ns.to_le_bytes());
        out[16] = 16;
        out[17..].copy_from_slice(&self.gid);
        out
    }

    /// Parses the wire bytes.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, DecodeError> {
        if bytes.len() != RMW_ATTACHMENT_LEN {
            return Err(DecodeError::Invalid(format!(
                "rmw_zenoh attachment must be {RMW_ATTACHMENT_LEN} bytes, got {}",
                bytes.len()
            )));
        }
        if bytes[16] != 16 {
            return Err(DecodeError::Invalid(format!(
                "rmw_zenoh GID length must be 16, got {}",
                bytes[16]
            )));
        }
        let word = |at: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&bytes[at..at + 8]);
            i64::from_le_bytes(b)
        };
        let mut gid = [0u8; 16];
        gid.copy_from_slice(&bytes[17..]);
        Ok(Self {
            sequence: word(0),
            source_timestamp_ns: word(8),
            gid,
        })
    }
}

/// A publisher's identity: numbers its publications like rmw_zenoh does.
#[derive(Debug)]
pub struct RmwPublisherId {
    gid: [u8; 16],
    sequence: AtomicI64,
}

impl RmwPublisherId {
    /// A fresh random GID.
    pub fn random() -> Self {
        Self {
            gid: rand::random(),
            sequence: AtomicI64::new(0),
        }
    }

    /// The GID.
    pub fn gid(&self) -> [u8; 16] {
        self.gid
    }

    /// The attachment of the next publication, stamped now.
    pub fn next_attachment(&self) -> RmwAttachment {
        let sequence = self.sequence.fetch_add(1, Ordering::Relaxed) + 1;
        let source_timestamp_ns = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
            .unwrap_or(0);
        RmwAttachment {
            sequence,
            source_timestamp_ns,
            gid: self.gid,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rmw_zenoh_keys_follow_the_documented_layout() -> Result<(), ContractError> {
        let graph = RosGraph::new(KeyStyle::RmwZenoh { domain_id: 0 }, "")?;
        assert_eq!(
            graph.publication_key("cmd_vel", RosType::Twist)?,
            "0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
        );
        let graph = RosGraph::new(KeyStyle::RmwZenoh { domain_id: 7 }, "/rosbot")?;
        assert_eq!(
            graph.subscription_key("camera/color/image_raw", RosType::Image)?,
            "7/rosbot/camera/color/image_raw/sensor_msgs::msg::dds_::Image_/*"
        );
        // Absolute names ignore the namespace.
        assert_eq!(
            graph.subscription_key("/odom", RosType::Odometry)?,
            "7/odom/nav_msgs::msg::dds_::Odometry_/*"
        );
        Ok(())
    }

    #[test]
    fn bridge_keys_are_the_topic_name() -> Result<(), ContractError> {
        let plain = RosGraph::new(KeyStyle::Bridge { prefix: None }, "")?;
        assert_eq!(
            plain.publication_key("/cmd_vel", RosType::Twist)?,
            "cmd_vel"
        );
        let prefixed = RosGraph::new(
            KeyStyle::Bridge {
                prefix: Some("site_a".into()),
            },
            "rosbot",
        )?;
        assert_eq!(
            prefixed.subscription_key("odom", RosType::Odometry)?,
            "site_a/rosbot/odom"
        );
        // The bridge's namespace written as a ROS name (found by fuzzing).
        let slashed = RosGraph::new(
            KeyStyle::Bridge {
                prefix: Some("/site_a".into()),
            },
            "",
        )?;
        assert_eq!(
            slashed.subscription_key("/odom", RosType::Odometry)?,
            "site_a/odom"
        );
        Ok(())
    }

    #[test]
    fn bad_ros_names_are_typed_errors() {
        for bad in ["", "/", "a//b", "a/", "cmd vel", "*", "a/**", "1abc", "@v1"] {
            let graph = RosGraph::new(KeyStyle::default(), "");
            let result = graph.and_then(|g| g.publication_key(bad, RosType::Twist));
            assert!(
                matches!(result, Err(ContractError::InvalidRosName(_))),
                "{bad:?} gave {result:?}"
            );
        }
        assert!(RosGraph::new(KeyStyle::default(), "ns/*").is_err());
    }

    #[test]
    fn attachment_round_trips_byte_for_byte() -> Result<(), DecodeError> {
        let a = RmwAttachment {
            sequence: 0x0102_0304_0506_0708,
            source_timestamp_ns: 1_700_000_000_123_456_789,
            gid: [0xAB; 16],
        };
        let bytes = a.to_bytes();
        assert_eq!(&bytes[..8], &[8, 7, 6, 5, 4, 3, 2, 1]);
        assert_eq!(bytes[16], 16);
        assert_eq!(RmwAttachment::from_bytes(&bytes)?, a);
        assert!(RmwAttachment::from_bytes(&bytes[..32]).is_err());
        let mut wrong_len = bytes;
        wrong_len[16] = 8;
        assert!(RmwAttachment::from_bytes(&wrong_len).is_err());
        let id = RmwPublisherId::random();
        assert_eq!(id.next_attachment().sequence, 1);
        assert_eq!(id.next_attachment().sequence, 2);
        Ok(())
    }
}
