//! What the parity tests share: scratch directories and episodes recorded
//! by an embedded twin with a given profile.

use offworld_runtime::Resolution;
use std::path::Path;

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::{connect, Target};
use offworld_parity::recorded::RecordedEpisode;
use offworld_runtime::msg::{Action, Channels, DepthFormat, ObsOptions, OpenRequest, Seed};
use offworld_sim_twin::TwinProfile;

/// A scratch directory, removed on drop.
pub use offworld_test_support::ScratchDir as Scratch;

/// What to record.
pub struct Recording<'a> {
    pub task: &'a str,
    /// Camera (width, height).
    pub resolution: Resolution,
    pub channels: Channels,
    pub episodes: u64,
    /// At most this many steps per episode.
    pub steps: u32,
    /// Seeds the resets (`seed + episode`) and the random actions.
    pub seed: u64,
}

/// Records episodes of seeded random discrete actions from an embedded
/// twin with `profile` into `dir`.
pub async fn record(dir: &Path, profile: TwinProfile, what: &Recording<'_>) {
    let connection = connect(
        Target::Embedded {
            task: what.task.into(),
            resolution: what.resolution,
            count: 1,
            record: Some(dir.to_owned()),
            twin_profile: profile,
        },
        what.task,
    )
    .await
    .expect("embedded twin recording");
    let Resolution { width, height } = what.resolution;
    let request = OpenRequest {
        experiment_name: "parity".into(),
        ..OpenRequest::anonymous(ObsOptions {
            channels: what.channels,
            height,
            width,
            depth_format: DepthFormat::Meters,
        })
    };
    let mut client = EnvClient::open(
        &connection.session,
        &connection.envs[0],
        request,
        ClientTimeouts::default(),
    )
    .await
    .expect("open");
    // xorshift64: the same actions for the same seed, without a dependency.
    let mut state = 0x9e37_79b9_7f4a_7c15_u64 ^ what.seed;
    for episode in 0..what.episodes {
        client
            .reset(Seed::Fixed(what.seed + episode))
            .await
            .expect("reset");
        for _ in 0..what.steps {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let reply = client
                .step(Action::Discrete((state % 4) as i64))
                .await
                .expect("step");
            if reply.terminated || reply.truncated {
                break;
            }
        }
    }
    client.close().await.expect("close");
}

/// Every episode recorded under `dir`, read.
pub fn episodes(dir: &Path) -> Vec<RecordedEpisode> {
    offworld_recorder::read::episode_files(dir)
        .expect("files")
        .iter()
        .map(|f| RecordedEpisode::read(f).expect("episode"))
        .collect()
}
