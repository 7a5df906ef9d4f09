//! What people watching read: the camera's preview (an env's `obs` frames
//! thinned) and the viewers' copies of its commands, poses and odometry.
//!
//! Every `obs` frame is delivered [`Delivery::Every`] (Zenoh `Block`): the
//! controller cannot do without one, so a reader too slow for that stream
//! slows its publisher, and a sim twin stepping thousands of times a second
//! sends every reader every frame. A viewer (a live monitor, the web page's
//! thumbnails) wants a few dozen frames a second and must never slow a
//! step: it subscribes to [`Topic::Preview`] instead, where the twin or
//! robot agent republishes the same bytes at most once every
//! [`PREVIEW_PERIOD`] (a frame skipped for being early is held and put
//! when its period ends, unless a newer one replaces it: a viewer always
//! ends on the newest frame), [`Delivery::Latest`] at [`PREVIEW_PRIORITY`]
//! (behind `obs`, faults and acknowledgements on every link), and only
//! while a subscriber matches (Zenoh's matching status), so with nobody
//! watching a frame costs one atomic load.
//!
//! The other streams delivered `Every` — `cmd`, and the `pose` and `odom`
//! answering it — have a viewers' copy too ([`Topic::viewers_copy`],
//! [`WatchedPublisher`]): every message, not thinned (a few small ones a
//! step), `Latest` at [`PREVIEW_PRIORITY`], put only while watched. Their
//! publishers' streams between commands (tracker poses, the base's
//! odometry) are copied alike, so a viewer reads the copies only. A viewer
//! reading an original would hold its publisher up whenever it stalls: a
//! frozen live monitor held every step of its env through the router for
//! the 5 s Zenoh waits before closing a blocked link.
//!
//! The overhead views (`overhead/<camera>`) are streams for viewers only,
//! delivered alike ([`ViewerCopy::declare_on`]); the sim twin and the
//! emulated enclosure render theirs only while watched ([`Watch`]).
//!
//! A congested link to a viewer costs the publisher Zenoh's drop patience
//! (`session::PATIENT_DROP_US`) once; until that link's queue drains, the
//! next previews to it are dropped at once (Zenoh marks the queue
//! congested).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvError, RecvTimeoutError};
use std::sync::Arc;
use std::time::{Duration, Instant};

use zenoh::bytes::ZBytes;
use zenoh::pubsub::Publisher;
use zenoh::qos::Priority;
use zenoh::{Session, Wait};

use crate::codec;
use crate::keys::{EnvId, Topic};
use crate::msg::SeqTag;
use crate::seal::Sealer;
use crate::wire::{self, Delivery, RequestError};

/// At most one preview frame this often (50 a second: what a viewer shows).
pub const PREVIEW_PERIOD: Duration = Duration::from_millis(20);

/// The priority of every viewers' copy (the preview, `preview_cmd`,
/// `preview_pose`, `preview_odom`) and of the overhead views: below Zenoh's default (`Data`), where
/// `obs`, `odom`, faults and e-stop acknowledgements travel: a link queues
/// each priority apart and sends the higher first.
pub const PREVIEW_PRIORITY: Priority = Priority::DataLow;

/// At most one frame a period: the first frame offered once `period` has
/// passed since the last one taken is taken.
#[derive(Debug, Clone)]
pub struct Pacer {
    period: Duration,
    last: Option<Instant>,
}

impl Pacer {
    /// A pacer taking its first frame at once.
    pub fn new(period: Duration) -> Self {
        Self { period, last: None }
    }

    /// Whether a frame offered at `now` is taken (it then counts as the
    /// last one).
    pub fn take(&mut self, now: Instant) -> bool {
        if self.wait(now).is_some() {
            return false;
        }
        self.last = Some(now);
        true
    }

    /// How long from `now` until a frame would be taken; `None`: at once.
    pub fn wait(&self, now: Instant) -> Option<Duration> {
        let next = self.last? + self.period;
        (next > now).then(|| next - now)
    }
}

/// The viewers' copy of one of an env's topics ([`Topic::viewers_copy`]),
/// or a stream for viewers only (an overhead camera's,
/// [`ViewerCopy::declare_on`]): `Latest` at [`PREVIEW_PRIORITY`], put only
/// while a subscriber matches.
pub struct ViewerCopy {
    publisher: Publisher<'static>,
    /// Whether a subscriber matches, kept by Zenoh's matching listener
    /// (which lives as long as the publisher).
    watched: Watch,
}

/// Whether a [`ViewerCopy`] is watched, for a thread other than its
/// publisher's: a loop that renders a view only while someone watches and
/// hands it to another thread to put.
#[derive(Debug, Clone, Default)]
pub struct Watch(Arc<AtomicBool>);

impl Watch {
    /// Whether anyone subscribes to the stream now.
    pub fn watched(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
}

impl ViewerCopy {
    /// Declares the copy of `env`'s `topic` on `session` and follows whether
    /// anyone subscribes to it (local or remote subscribers alike). An
    /// error for a topic viewers read as it is.
    pub fn declare(session: &Session, env: &EnvId, topic: Topic) -> zenoh::Result<Self> {
        let copy = topic
            .viewers_copy()
            .ok_or_else(|| format!("`{}` has no viewers' copy", topic.as_str()))?;
        Self::declare_on(session, env.key(copy))
    }

    /// A stream for viewers only on `key` (an overhead camera's), delivered
    /// as the copies are: `Latest`, at [`PREVIEW_PRIORITY`], only while
    /// watched.
    pub fn declare_on(session: &Session, key: String) -> zenoh::Result<Self> {
        let publisher = wire::publisher(session, key, Delivery::Latest)
            .priority(PREVIEW_PRIORITY)
            .wait()?;
        let watched = Watch::default();
        let flag = watched.0.clone();
        publisher
            .matching_listener()
            .callback(move |status| flag.store(status.matching(), Ordering::Relaxed))
            .background()
            .wait()?;
        Ok(Self { publisher, watched })
    }

    /// Whether anyone subscribes to the copy now.
    pub fn watched(&self) -> bool {
        self.watched.watched()
    }

    /// Whether it is watched, for other threads.
    pub fn watch(&self) -> Watch {
        self.watched.clone()
    }

    /// Puts `payload` (and its `attachment`) if someone watches; returns
    /// whether it went out. A failed put is logged, never fatal: the copy
    /// is only for people watching.
    pub fn put(&self, payload: ZBytes, attachment: Option<ZBytes>) -> bool {
        if !self.watched() {
            return false;
        }
        match self.publisher.put(payload).attachment(attachment).wait() {
            Ok(()) => true,
            Err(e) => {
                tracing::debug!("put on {} failed: {e}", self.publisher.key_expr());
                false
            }
        }
    }
}

/// A publisher of an env's `cmd`, `pose` or `odom` that also puts each
/// message, the same bytes and tag, on the topic's [`ViewerCopy`] while
/// someone watches it, after the original went out. A copy's put can wait
/// Zenoh's drop patience (50 ms) on a link congested at its priority: an
/// answer's copies are put once the whole answer is out
/// ([`WatchedPublisher::answer_tagged`]).
pub struct WatchedPublisher {
    publisher: Publisher<'static>,
    /// `None` if it could not be declared: viewers then see nothing of
    /// this topic, and the publisher works on.
    copy: Option<ViewerCopy>,
}

/// An answer's copy for viewers, to be put once the whole answer is out.
#[must_use = "put it once the answer is out"]
pub struct DueCopy<'a> {
    copy: Option<&'a ViewerCopy>,
    payload: ZBytes,
    tag: ZBytes,
}

impl DueCopy<'_> {
    /// Puts the copy if someone watches; returns whether it went out.
    pub fn put(self) -> bool {
        self.copy
            .is_some_and(|copy| copy.put(self.payload, Some(self.tag)))
    }
}

impl WatchedPublisher {
    /// `publisher`, declared on `env`'s `topic`, with the topic's copy (a
    /// copy that cannot be declared is logged and left out).
    pub fn new(
        session: &Session,
        env: &EnvId,
        topic: Topic,
        publisher: Publisher<'static>,
    ) -> Self {
        let copy = ViewerCopy::declare(session, env, topic)
            .inspect_err(|e| {
                tracing::warn!(
                    "no viewers' copy of {}: {e}; live monitors will not show it",
                    publisher.key_expr()
                )
            })
            .ok();
        Self { publisher, copy }
    }

    /// Whether anyone subscribes to the viewers' copy now.
    pub fn watched(&self) -> bool {
        self.copy.as_ref().is_some_and(ViewerCopy::watched)
    }

    /// The original's key.
    pub fn key_expr(&self) -> &str {
        self.publisher.key_expr().as_str()
    }

    /// Publishes `msg` ([`wire::publish`]), then its copy.
    pub fn publish<T: serde::Serialize>(&self, msg: &T) -> Result<(), RequestError> {
        self.publish_sealed(msg, None)
    }

    /// Publishes `msg` tagged with the command it answers
    /// ([`wire::publish_tagged`]); its copy is put by the [`DueCopy`]
    /// returned, once the rest of the answer is out.
    pub fn answer_tagged<T: serde::Serialize>(
        &self,
        msg: &T,
        tag: SeqTag,
    ) -> Result<DueCopy<'_>, RequestError> {
        let tag = ZBytes::from(codec::encode(&tag)?);
        let payload = self.send(codec::encode(msg)?, Some(tag.clone()))?;
        Ok(DueCopy {
            copy: self.copy.as_ref(),
            payload,
            tag,
        })
    }

    /// Publishes `msg`, sealed by `sealer` when there is one (as
    /// [`wire::put_sealed`] seals), then its copy, unsealed (a seal is made
    /// for the original's key, and nobody acts on a copy).
    pub fn publish_sealed<T: serde::Serialize>(
        &self,
        msg: &T,
        sealer: Option<&Sealer>,
    ) -> Result<(), RequestError> {
        let bytes = codec::encode(msg)?;
        let seal = sealer.map(|s| ZBytes::from(s.seal(self.key_expr(), &bytes, &[])));
        let payload = self.send(bytes, seal)?;
        self.copy_now(payload, None);
        Ok(())
    }

    /// Puts the original; returns its payload for the copy.
    fn send(&self, bytes: Vec<u8>, attachment: Option<ZBytes>) -> Result<ZBytes, RequestError> {
        let payload = ZBytes::from(bytes);
        self.publisher
            .put(payload.clone())
            .attachment(attachment)
            .wait()
            .map_err(|e| RequestError::Zenoh(e.to_string()))?;
        Ok(payload)
    }

    fn copy_now(&self, payload: ZBytes, attachment: Option<ZBytes>) {
        if let Some(copy) = &self.copy {
            copy.put(payload, attachment);
        }
    }
}

/// Publishes an env's preview: offered every frame, it puts one a
/// [`PREVIEW_PERIOD`] while someone subscribes, none otherwise. Its owner's
/// loop puts a held frame when its period ends with no newer one offered (a
/// sim paused between steps): waiting with
/// [`PreviewPublisher::recv_flushing`] (the robot agent), or with
/// [`PreviewPublisher::held_for`] and [`PreviewPublisher::flush`] (the sim
/// twin, whose frames may be offered on other threads).
pub struct PreviewPublisher {
    copy: ViewerCopy,
    pacer: Pacer,
    /// The newest frame offered too early, put when its period ends.
    held: Option<ZBytes>,
}

impl PreviewPublisher {
    /// Declares `env`'s preview publisher on `session` and follows whether
    /// anyone subscribes to it (local or remote subscribers alike).
    pub fn declare(session: &Session, env: &EnvId) -> zenoh::Result<Self> {
        Ok(Self {
            copy: ViewerCopy::declare(session, env, Topic::Obs)?,
            pacer: Pacer::new(PREVIEW_PERIOD),
            held: None,
        })
    }

    /// Whether anyone subscribes to the preview now.
    pub fn watched(&self) -> bool {
        self.copy.watched()
    }

    /// Offers the encoded `obs` frame just published; returns whether it
    /// went out as the preview now. An early one is held for
    /// [`PreviewPublisher::flush`], replacing any frame held before.
    pub fn offer(&mut self, frame: &ZBytes) -> bool {
        // A replaced frame's buffer goes back to its pool now.
        self.held = None;
        if !self.watched() {
            return false;
        }
        if !self.pacer.take(Instant::now()) {
            self.held = Some(frame.clone());
            return false;
        }
        self.copy.put(frame.clone(), None)
    }

    /// How long until the held frame is due (zero: now); `None` when no
    /// frame is held.
    pub fn held_for(&self) -> Option<Duration> {
        self.held
            .as_ref()
            .map(|_| self.pacer.wait(Instant::now()).unwrap_or_default())
    }

    /// Puts the held frame if its period has ended and someone still
    /// watches; returns whether it went out.
    pub fn flush(&mut self) -> bool {
        let now = Instant::now();
        if self.held.is_none() || self.pacer.wait(now).is_some() {
            return false;
        }
        match self.held.take() {
            Some(frame) if self.watched() && self.pacer.take(now) => self.copy.put(frame, None),
            _ => false,
        }
    }

    /// The next item from `items`, putting the held frame meanwhile when
    /// its period ends; an error once every sender is gone.
    pub fn recv_flushing<T>(&mut self, items: &Receiver<T>) -> Result<T, RecvError> {
        loop {
            let Some(wait) = self.held_for() else {
                return items.recv();
            };
            match items.recv_timeout(wait) {
                Ok(item) => return Ok(item),
                Err(RecvTimeoutError::Timeout) => {
                    self.flush();
                }
                Err(RecvTimeoutError::Disconnected) => return Err(RecvError),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pacer_takes_the_first_frame_then_one_a_period() {
        let start = Instant::now();
        let at = |ms: u64| start + Duration::from_millis(ms);
        let mut pacer = Pacer::new(Duration::from_millis(20));
        assert_eq!(pacer.wait(at(0)), None);
        let taken: Vec<u64> = [0, 5, 19, 20, 21, 39, 41, 100, 100]
            .into_iter()
            .filter(|&ms| pacer.take(at(ms)))
            .collect();
        // 40 is due at 40 (20 + 20): 39 is early, 41 is taken.
        assert_eq!(taken, vec![0, 20, 41, 100]);
        assert_eq!(pacer.wait(at(100)), Some(Duration::from_millis(20)));
        assert_eq!(pacer.wait(at(115)), Some(Duration::from_millis(5)));
        assert_eq!(pacer.wait(at(120)), None);
        // A clock read earlier than the last taken (another thread's
        // instant) is within the period, not a panic.
        assert!(!pacer.take(at(50)));
    }
}
