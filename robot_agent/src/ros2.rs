//! The production backend: a ROS 2 robot reached over Zenoh (rmw_zenoh or
//! zenoh-bridge-ros2dds keys, CDR payloads). Publishes
//! `geometry_msgs/Twist`, subscribes `sensor_msgs/Image` colour and depth and
//! `nav_msgs/Odometry`.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use offworld_runtime::codec;
use offworld_runtime::msg::{Image, Odometry, Twist};
use offworld_runtime::ros2::{KeyStyle, RmwPublisherId, RobotTopics, RosGraph, RosType};
use offworld_runtime::wire::{self, Delivery};
use tokio::sync::watch;
use zenoh::bytes::Encoding;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;
use zenoh::Session;

use crate::error::AgentError;
use crate::hardware::{Received, RobotHardware, Sensors};
use crate::limiter::Velocity;

/// A ROS 2 robot over Zenoh.
pub struct Ros2Robot {
    cmd_vel: CmdVelPublisher,
    sensors: watch::Receiver<Sensors>,
    rejected: Arc<AtomicU64>,
    _subscribers: Vec<Subscriber<()>>,
}

impl Ros2Robot {
    /// Subscribes the robot's sensor topics and prepares its velocity topic.
    pub async fn connect(
        session: &Session,
        graph: &RosGraph,
        topics: &RobotTopics,
    ) -> Result<Self, AgentError> {
        let (tx, sensors) = watch::channel(Sensors::default());
        let tx = Arc::new(tx);
        let rejected = Arc::new(AtomicU64::new(0));
        let mut subscribers = Vec::new();
        for (topic, slot) in [(&topics.color, Slot::Color), (&topics.depth, Slot::Depth)] {
            let key = graph.subscription_key(topic, RosType::Image)?;
            let (tx, rejected) = (tx.clone(), rejected.clone());
            let sub = session
                .declare_subscriber(key.clone())
                .callback(move |sample: Sample| {
                    let image = codec::decode_payload::<Image>(sample.payload())
                        .map_err(|e| e.to_string())
                        .and_then(|img| img.validate().map(|_| img).map_err(|e| e.to_string()));
                    match image {
                        Ok(img) => {
                            let received = Some(Received {
                                msg: Arc::new(img),
                                at: Instant::now(),
                            });
                            tx.send_modify(|s| match slot {
                                Slot::Color => s.color = received,
                                Slot::Depth => s.depth = received,
                            });
                        }
                        Err(e) => {
                            rejected.fetch_add(1, Ordering::Relaxed);
                            tracing::warn!(%key, "rejected an image: {e}");
                        }
                    }
                })
                .await?;
            subscribers.push(sub);
        }
        let key = graph.subscription_key(&topics.odom, RosType::Odometry)?;
        let (odom_tx, odom_rejected) = (tx.clone(), rejected.clone());
        let odom = session
            .declare_subscriber(key.clone())
            .callback(move |sample: Sample| {
                match codec::decode_payload::<Odometry>(sample.payload()) {
                    Ok(o) => odom_tx.send_modify(|s| {
                        s.odom = Some(Received {
                            msg: Arc::new(o),
                            at: Instant::now(),
                        })
                    }),
                    Err(e) => {
                        odom_rejected.fetch_add(1, Ordering::Relaxed);
                        tracing::warn!(%key, "rejected odometry: {e}");
                    }
                }
            })
            .await?;
        subscribers.push(odom);
        Ok(Self {
            cmd_vel: CmdVelPublisher::new(session, graph, topics)?,
            sensors,
            rejected,
            _subscribers: subscribers,
        })
    }

    /// Sensor messages rejected as malformed so far.
    pub fn rejected(&self) -> u64 {
        self.rejected.load(Ordering::Relaxed)
    }
}

#[derive(Clone, Copy)]
enum Slot {
    Color,
    Depth,
}

impl RobotHardware for Ros2Robot {
    async fn drive(&self, velocity: Velocity) -> Result<(), AgentError> {
        self.cmd_vel.send(velocity).await
    }

    fn sensors(&self) -> watch::Receiver<Sensors> {
        self.sensors.clone()
    }
}

/// The base's velocity topic as a ROS 2 publisher would write it: the
/// agent drives through it, and the base guard zeroes through it.
pub struct CmdVelPublisher {
    session: Session,
    key: String,
    publisher: RmwPublisherId,
    rmw: bool,
}

impl CmdVelPublisher {
    /// A publisher on `topics.cmd_vel` of `graph`.
    pub fn new(
        session: &Session,
        graph: &RosGraph,
        topics: &RobotTopics,
    ) -> Result<Self, AgentError> {
        Ok(Self {
            session: session.clone(),
            key: graph.publication_key(&topics.cmd_vel, RosType::Twist)?,
            publisher: RmwPublisherId::random(),
            rmw: matches!(graph.style(), KeyStyle::RmwZenoh { .. }),
        })
    }

    /// Commands `velocity` once (the base holds it, or times it out).
    pub async fn send(&self, velocity: Velocity) -> Result<(), AgentError> {
        let twist = Twist::planar(velocity.linear, velocity.angular);
        let bytes = codec::encode(&twist).map_err(|e| AgentError::Encode(e.to_string()))?;
        let mut put = self
            .session
            .put(&self.key, bytes)
            .encoding(Encoding::APPLICATION_CDR)
            // The watchdog's stop rides here: never dropped, never queued
            // behind the camera stream on the robot's router.
            .congestion_control(Delivery::Every.congestion_control())
            .priority(wire::CONTROL_PRIORITY);
        if self.rmw {
            // rmw_zenoh subscribers read the sender's GID and sequence here.
            put = put.attachment(self.publisher.next_attachment().to_bytes().to_vec());
        }
        put.await?;
        Ok(())
    }
}
