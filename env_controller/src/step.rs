//! One command's life, with one owner: the command sent, its frame and pose
//! received, judged once, replied once. The env then records it and
//! accounts for the episode ([`crate::env`]); the link carries it
//! ([`crate::link`]).
//!
//! ```text
//!            its frame, the pose tagged with it already in (a twin)
//!   Sent ─────────────────────────────────────────────────▶ Judged ─▶ Replied
//!    │                         (the frame's thread: the fast path)  │
//!    │                                                             └▶ Due: the episode ends,
//!    │  its frame, no pose yet (a tracker's comes after it)             recorded before the reply
//!    ├─────────────────────────▶ Built ── its pose (the env's task) ─▶ Judged ─▶ Due
//!    │
//!    └── fault · robot gone · tracking lost · silence · timeout · stopping ─▶ Failed
//! ```
//!
//! The frame's thread and the env's task hand the step over through one
//! slot of the link: taking it from there is the commit point. A task that
//! gives up (a timeout, tracking lost) withdraws it; if the frame's thread
//! took it first and replied, the client has the step, so it stands.

use std::sync::Arc;

use offworld_runtime::codec::{self, Encoded};
use offworld_runtime::msg::{MotionCommand, ObsOptions, StepReply};
use offworld_runtime::pool::BufferPool;
use offworld_runtime::{wire, WireError};
use tokio::sync::oneshot;
use zenoh::bytes::ZBytes;
use zenoh::query::Query;

use crate::episode::{judge, step_info, Outcome};
use crate::link::{Frame, ObservationRequest, PoseSample, RobotLink};
use crate::task::Task;

/// What a command's answer is judged by, once, from the pose it reached.
pub trait Judge: Send + 'static {
    /// What the judge says.
    type Verdict: Send + 'static;
    /// The reply's fields before the observation.
    type Reply: serde::Serialize;

    /// Judges the pose that answered the command.
    fn judge(&self, pose: &PoseSample) -> Self::Verdict;

    /// The reply to send at once, unless the env must see the verdict
    /// first (an episode that ends is recorded before its reply).
    fn reply_now(verdict: &Self::Verdict) -> Option<&Self::Reply>;
}

/// The judge of a look around (a reset's first observation): no verdict,
/// and the env replies.
#[derive(Clone)]
pub struct Look;

impl Judge for Look {
    type Verdict = ();
    type Reply = ();

    fn judge(&self, _pose: &PoseSample) {}

    fn reply_now(_verdict: &()) -> Option<&()> {
        None
    }
}

/// A step of an episode, judged by its task's rules.
#[derive(Clone)]
pub struct StepJudge {
    /// The task whose rules judge.
    pub task: Arc<Task>,
    /// The client's request number.
    pub seq: u64,
    /// The episode.
    pub episode_id: u64,
    /// This step's number in the episode (1-based).
    pub step: u32,
    /// The observation's options (the reply's shape).
    pub obs: ObsOptions,
    /// Whether `info` carries the robot's ground truth.
    pub share_pose: bool,
}

/// A step judged: its outcome, and the reply that says it.
#[derive(Debug, Clone)]
pub struct Judgement {
    /// Reward and end.
    pub outcome: Outcome,
    /// The reply's fields before the observation.
    pub reply: StepReply,
}

impl Judge for StepJudge {
    type Verdict = Judgement;
    type Reply = StepReply;

    fn judge(&self, pose: &PoseSample) -> Judgement {
        let pose = pose.planar();
        let outcome = judge(&self.task, pose.x, pose.y, self.step);
        let info = step_info(
            &self.task,
            self.episode_id,
            self.step,
            &pose,
            Some(&outcome),
            self.share_pose,
        );
        let reply = StepReply {
            seq: self.seq,
            reward: outcome.reward,
            terminated: outcome.terminated,
            truncated: outcome.truncated,
            info,
            observation: self.obs.shape(),
        };
        Judgement { outcome, reply }
    }

    fn reply_now(verdict: &Judgement) -> Option<&StepReply> {
        verdict.outcome.end.is_none().then_some(&verdict.reply)
    }
}

/// A command, and what to make of its answer.
pub struct Plan<J> {
    motion: MotionCommand,
    observation: ObservationRequest,
    judge: J,
    reply_to: Option<Query>,
}

impl Plan<Look> {
    /// A command answered with an observation and a pose, judged by no one.
    pub fn observe(motion: MotionCommand, observation: ObservationRequest) -> Self {
        Self::judged(motion, observation, Look, None)
    }
}

impl<J: Judge> Plan<J> {
    /// A command judged by `judge`; with `reply_to`, replied from where its
    /// frame is received when the pose tagged with it is in by then and
    /// the judge lets it ([`Judge::reply_now`]).
    pub fn judged(
        motion: MotionCommand,
        observation: ObservationRequest,
        judge: J,
        reply_to: Option<Query>,
    ) -> Self {
        Self {
            motion,
            observation,
            judge,
            reply_to,
        }
    }

    /// Sends the command over `link` and follows it to its answer.
    pub async fn run(self, link: &RobotLink) -> Result<Answered<J::Verdict>, WireError> {
        link.ready_to_send().await?;
        let seq = self.motion.seq;
        let (handed, stage) = oneshot::channel();
        link.expect(Box::new(InFlight {
            seq,
            observation: self.observation,
            judge: self.judge,
            reply_to: self.reply_to,
            handed,
        }));
        match link.send_and_await(&self.motion).await {
            Ok(pose) => match stage.await {
                Ok(Stage::Judged {
                    frame,
                    pose,
                    verdict,
                    reply,
                }) => Ok(Answered {
                    pose,
                    frame,
                    verdict,
                    reply,
                }),
                Ok(Stage::Built {
                    frame,
                    observation,
                    judge,
                }) => Ok(Answered {
                    verdict: judge.judge(&pose),
                    pose,
                    frame,
                    reply: Reply::Due(observation?),
                }),
                // The slot holds one command, replaced only by the next,
                // which waits for this one: only a panic while its frame
                // was handled drops it unheard.
                Err(_) => Err(WireError::internal(format!(
                    "command {seq}'s frame was taken and never handed over"
                ))),
            },
            Err(failed) => {
                if link.withdraw(seq) {
                    return Err(failed);
                }
                // Its frame arrived as this gave up: if the frame's thread
                // replied, the client has the step, so the step stands.
                match stage.await {
                    Ok(Stage::Judged {
                        frame,
                        pose,
                        verdict,
                        reply: Reply::Sent,
                    }) => Ok(Answered {
                        pose,
                        frame,
                        verdict,
                        reply: Reply::Sent,
                    }),
                    _ => Err(failed),
                }
            }
        }
    }
}

/// A command's answer: the pose it reached, its frame, the verdict, and
/// whether its reply has gone.
pub struct Answered<V> {
    /// The robot's pose after the motion.
    pub pose: PoseSample,
    /// The camera frame that answered (kept as received, for the recorder).
    pub frame: Arc<Frame>,
    /// What the judge said.
    pub verdict: V,
    /// The reply: sent, or due with this observation.
    pub reply: Reply,
}

impl<V> Answered<V> {
    /// The reply to send: `fields`, then the observation; `None` when it
    /// was sent where the frame was received.
    pub fn reply_with<T: serde::Serialize>(
        &self,
        fields: &T,
    ) -> Result<Option<Encoded<T>>, WireError> {
        match &self.reply {
            Reply::Sent => Ok(None),
            Reply::Due(observation) => codec::encode_with_tail(fields, observation.clone())
                .map(Some)
                .map_err(|e| WireError::internal(e.to_string())),
        }
    }
}

/// Where a command's reply stands.
pub enum Reply {
    /// Sent from the frame's thread.
    Sent,
    /// Still to send, with this observation.
    Due(ZBytes),
}

/// A command in flight, as the frame's thread finds it in the link's slot.
pub(crate) trait AwaitingFrame: Send {
    /// The command whose frame it awaits.
    fn seq(&self) -> u64;

    /// Its frame arrived, with `pose` the latest pose while tracking holds
    /// (the caller leaves it out otherwise): builds the observation, judges
    /// and replies when that pose is tagged with the command, and hands the
    /// step back to the env's task. `announce` tells the task that the
    /// frame is in: after the reply on the fast path (the task has nothing
    /// to do before), before building otherwise (the task reads the pose
    /// meanwhile).
    fn on_frame(
        self: Box<Self>,
        frame: Arc<Frame>,
        buffers: &BufferPool,
        pose: Option<PoseSample>,
        announce: &dyn Fn(Arc<Frame>),
    );
}

/// What the frame's thread hands back.
enum Stage<J: Judge> {
    /// The observation built (or not); the task judges the pose when it
    /// has it, with the judge handed back.
    Built {
        frame: Arc<Frame>,
        observation: Result<ZBytes, WireError>,
        judge: J,
    },
    /// Judged from the pose tagged with the command.
    Judged {
        frame: Arc<Frame>,
        pose: PoseSample,
        verdict: J::Verdict,
        reply: Reply,
    },
}

struct InFlight<J: Judge> {
    seq: u64,
    observation: ObservationRequest,
    judge: J,
    reply_to: Option<Query>,
    handed: oneshot::Sender<Stage<J>>,
}

impl<J: Judge> AwaitingFrame for InFlight<J> {
    fn seq(&self) -> u64 {
        self.seq
    }

    fn on_frame(
        self: Box<Self>,
        frame: Arc<Frame>,
        buffers: &BufferPool,
        pose: Option<PoseSample>,
        announce: &dyn Fn(Arc<Frame>),
    ) {
        let InFlight {
            seq,
            observation: request,
            judge,
            reply_to,
            handed,
        } = *self;
        let tagged = pose.filter(|p| p.seq == Some(seq));
        // The task may have given up: nobody to tell (each `send` below).
        match (tagged, &reply_to) {
            (Some(pose), Some(query)) => {
                let stage = match frame.build(&request, buffers) {
                    Ok(observation) => {
                        let verdict = judge.judge(&pose);
                        let reply = reply_now(query, J::reply_now(&verdict), observation);
                        Stage::Judged {
                            frame: frame.clone(),
                            pose,
                            verdict,
                            reply,
                        }
                    }
                    Err(e) => Stage::Built {
                        frame: frame.clone(),
                        observation: Err(e),
                        judge,
                    },
                };
                // Handed over before the task wakes: it finds the step done.
                let _ = handed.send(stage);
                announce(frame);
            }
            _ => {
                announce(frame.clone());
                let _ = handed.send(Stage::Built {
                    observation: frame.build(&request, buffers),
                    frame,
                    judge,
                });
            }
        }
    }
}

/// Replies to `query` with `fields` and `observation`, if given fields;
/// else (or if they cannot be encoded) leaves the reply due.
fn reply_now<T: serde::Serialize>(query: &Query, fields: Option<&T>, observation: ZBytes) -> Reply {
    let Some(encoded) = fields.and_then(|f| codec::encode_with_tail(f, observation.clone()).ok())
    else {
        return Reply::Due(observation);
    };
    if let Err(e) = wire::reply_encoded_now(query, Ok(encoded)) {
        tracing::warn!(key = %query.key_expr(), "step reply failed: {e}");
    }
    Reply::Sent
}
