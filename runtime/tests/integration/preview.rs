//! The camera's preview over real Zenoh sessions: nothing is put while
//! nobody subscribes; a subscriber (remote or in the same session) gets the
//! very bytes offered, at most one a period; it stops when they leave.
//! The viewers' copies of commands, poses and odometry carry each message
//! with its tag, droppable and at low priority, only while watched.

use crate::common;

use std::time::{Duration, Instant};

use offworld_runtime::codec;
use offworld_runtime::msg::CameraFrame;
use offworld_runtime::msg::{PoseStamped, SeqTag};
use offworld_runtime::preview::{
    PreviewPublisher, ViewerCopy, WatchedPublisher, PREVIEW_PERIOD, PREVIEW_PRIORITY,
};
use offworld_runtime::session::loopback_pair;
use offworld_runtime::wire::{self, Delivery};
use offworld_runtime::{EnvId, Topic};
use zenoh::bytes::ZBytes;
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::qos::CongestionControl;
use zenoh::sample::Sample;

/// How long a declaration may take to reach the other session.
const PATIENCE: Duration = Duration::from_secs(10);

async fn until(what: &str, mut done: impl FnMut() -> bool) {
    let started = Instant::now();
    while !done() {
        assert!(
            started.elapsed() < PATIENCE,
            "{what}: not within {PATIENCE:?}"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_preview_goes_out_only_while_watched_and_at_most_once_a_period() -> anyhow::Result<()> {
    let (twin, viewer) = loopback_pair().await?;
    let env = EnvId::sim(&format!("preview-{}", std::process::id()))?;
    let mut preview = PreviewPublisher::declare(&twin, &env).map_err(|e| anyhow::anyhow!(e))?;
    let frame = ZBytes::from(codec::encode(&common::camera_frame())?);

    assert!(!preview.watched());
    assert!(!preview.offer(&frame), "put with nobody watching");

    let sub = viewer
        .declare_subscriber(env.key(Topic::Preview))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    until("the remote subscriber is matched", || preview.watched()).await;
    // Offered as a sim twin offers its frames (far faster than the period),
    // for a bounded count: every one taken went out, and no more were taken
    // than periods passed.
    let started = Instant::now();
    let mut sent = 0_u32;
    for _ in 0..500 {
        sent += u32::from(preview.offer(&frame));
        tokio::time::sleep(Duration::from_micros(200)).await;
    }
    let periods = started.elapsed().as_secs_f64() / PREVIEW_PERIOD.as_secs_f64();
    assert!(sent >= 2, "the first frame at once, then one a period");
    assert!(
        f64::from(sent) <= periods.floor() + 1.0,
        "{sent} previews in {periods:.1} periods"
    );
    let mut received = 0;
    while received < sent {
        let sample = tokio::time::timeout(PATIENCE, sub.recv_async())
            .await?
            .map_err(|e| anyhow::anyhow!(e))?;
        assert_eq!(sample.encoding(), &zenoh::bytes::Encoding::APPLICATION_CDR);
        let got: CameraFrame = codec::decode_payload(sample.payload())?;
        assert_eq!(got, common::camera_frame());
        received += 1;
    }
    // The last frame offered, if early, is held (not put) until flushed.
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!(sub.try_recv().map_err(|e| anyhow::anyhow!(e))?.is_none());

    // The newest frame is the last one a viewer gets: one offered early is
    // put by `flush` once its period has ended.
    let newer = {
        let mut frame = common::camera_frame();
        frame.seq += 1;
        frame
    };
    if preview.flush() {
        // The loop's last frame, held.
        tokio::time::timeout(PATIENCE, sub.recv_async())
            .await?
            .map_err(|e| anyhow::anyhow!(e))?;
    }
    tokio::time::sleep(PREVIEW_PERIOD).await;
    assert!(preview.offer(&frame));
    if !preview.offer(&ZBytes::from(codec::encode(&newer)?)) {
        let wait = preview.held_for().expect("held");
        assert!(wait <= PREVIEW_PERIOD, "{wait:?}");
        tokio::time::sleep(wait).await;
        assert!(preview.flush());
    }
    assert_eq!(preview.held_for(), None);
    for expected in [common::camera_frame(), newer] {
        let sample = tokio::time::timeout(PATIENCE, sub.recv_async())
            .await?
            .map_err(|e| anyhow::anyhow!(e))?;
        let got: CameraFrame = codec::decode_payload(sample.payload())?;
        assert_eq!(got, expected);
    }

    // Gone: nothing more is put.
    sub.undeclare().await.map_err(|e| anyhow::anyhow!(e))?;
    until("the subscriber's departure is seen", || !preview.watched()).await;
    tokio::time::sleep(PREVIEW_PERIOD).await;
    assert!(!preview.offer(&frame));

    // A subscriber in the publisher's own session (an embedded monitor)
    // watches too.
    let local = twin
        .declare_subscriber(env.key(Topic::Preview))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    until("the local subscriber is matched", || preview.watched()).await;
    assert!(preview.offer(&frame));
    let sample = tokio::time::timeout(PATIENCE, local.recv_async())
        .await?
        .map_err(|e| anyhow::anyhow!(e))?;
    assert_eq!(sample.payload().to_bytes(), frame.to_bytes());
    Ok(())
}

/// The next sample `sub` receives (bounded wait).
async fn next(sub: &Subscriber<FifoChannelHandler<Sample>>) -> anyhow::Result<Sample> {
    tokio::time::timeout(PATIENCE, sub.recv_async())
        .await?
        .map_err(|e| anyhow::anyhow!(e))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewers_get_a_droppable_copy_of_each_message_only_while_watching() -> anyhow::Result<()> {
    let (twin, others) = loopback_pair().await?;
    let env = EnvId::sim(&format!("copy-{}", std::process::id()))?;
    let err = |e: zenoh::Error| anyhow::anyhow!(e);
    let pose = wire::publisher(&twin, env.key(Topic::Pose), Delivery::Every)
        .await
        .map_err(err)?;
    let pose = WatchedPublisher::new(&twin, &env, Topic::Pose, pose);
    assert!(
        ViewerCopy::declare(&twin, &env, Topic::Reward).is_err(),
        "viewers read `reward` itself"
    );
    let message = |seq: u64| {
        let mut msg = PoseStamped::default();
        msg.pose.position.x = seq as f64;
        msg
    };
    // Nobody watches: no copy is due.
    assert!(!pose.watched());
    assert!(!pose.answer_tagged(&message(1), SeqTag { seq: 1 })?.put());

    // The controller's subscription is declared first: it is routed once
    // the viewer's is (one session's declarations travel in order).
    let controller = others
        .declare_subscriber(env.key(Topic::Pose))
        .await
        .map_err(err)?;
    let viewer = others
        .declare_subscriber(env.key(Topic::PreviewPose))
        .await
        .map_err(err)?;
    until("the viewer is matched", || pose.watched()).await;
    // An answer's copy is put when due; a stream's at once.
    let due = pose.answer_tagged(&message(2), SeqTag { seq: 2 })?;
    assert!(due.put());
    pose.publish(&message(3))?;
    for (seq, tag) in [(2, Some(2)), (3, None)] {
        // Message 1, put before the controller subscribed, may still reach
        // it (it was in flight): the originals from 2 on are compared.
        let mut original = next(&controller).await?;
        if codec::decode_payload::<PoseStamped>(original.payload())? == message(1) {
            original = next(&controller).await?;
        }
        let copy = next(&viewer).await?;
        assert_eq!(copy.key_expr().as_str(), env.key(Topic::PreviewPose));
        assert_eq!(copy.payload().to_bytes(), original.payload().to_bytes());
        let got: PoseStamped = codec::decode_payload(copy.payload())?;
        assert_eq!(got, message(seq));
        assert_eq!(wire::decode_attachment::<SeqTag>(&copy).map(|t| t.seq), tag);
        assert_eq!(
            wire::decode_attachment::<SeqTag>(&original).map(|t| t.seq),
            tag
        );
        assert_eq!(copy.congestion_control(), CongestionControl::Drop);
        assert_eq!(copy.priority(), PREVIEW_PRIORITY);
        assert_eq!(original.congestion_control(), CongestionControl::Block);
    }
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!(viewer.try_recv().map_err(err)?.is_none(), "one copy each");
    assert!(controller.try_recv().map_err(err)?.is_none());
    // The viewer leaves: no copy is due any more.
    viewer.undeclare().await.map_err(err)?;
    until("the viewer has left", || !pose.watched()).await;
    assert!(!pose.answer_tagged(&message(4), SeqTag { seq: 4 })?.put());
    Ok(())
}
