//! `test_helper floods-tokens`: a trainer that declares liveliness tokens
//! under `alive/client/*` (its presence, which its credentials allow) by
//! the thousand, distinct ones, and drops them again, round after round:
//! a stranger trying to drown the controller in presence changes. Prints
//! `flooding` once the first 1,000 are out, then goes on until killed or
//! `--seconds` pass.
//!
//! ```text
//! test_helper floods-tokens -c trainer.json5 --connect quic/127.0.0.1:7447 \
//!     --cfg 'transport/auth/usrpwd/password:"…"' --env sim/a-0 --count 30000
//! ```

use std::io::Write;
use std::time::{Duration, Instant};

use offworld_program::CommonArgs;
use offworld_runtime::keys::EnvId;

/// Tokens out before `flooding` is printed.
const FIRST: u32 = 1_000;

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    common: CommonArgs,
    /// The env whose client tokens to flood (`<realm>/<env>`).
    #[arg(long)]
    env: EnvId,
    /// Distinct tokens declared a round (then all dropped).
    #[arg(long, default_value_t = 30_000)]
    count: u32,
    /// Stop after this long.
    #[arg(long, default_value_t = 120)]
    seconds: u64,
}

pub async fn run(args: Args) -> anyhow::Result<()> {
    let Args {
        common,
        env,
        count,
        seconds,
    } = args;
    let session = common
        .client_config()
        .open()
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    // Declared without yielding between tokens: as fast as one thread can.
    tokio::task::spawn_blocking(move || flood(&session, &env, count, Duration::from_secs(seconds)))
        .await?
}

fn flood(session: &zenoh::Session, env: &EnvId, count: u32, span: Duration) -> anyhow::Result<()> {
    let started = Instant::now();
    let mut round = 0u64;
    while started.elapsed() < span {
        let mut tokens = Vec::with_capacity(count as usize);
        for i in 0..count {
            let key = env.client_alive_key(&format!("flood{round}x{i}"))?;
            let token = zenoh::Wait::wait(session.liveliness().declare_token(key))
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            tokens.push(token);
            if round == 0 && i + 1 == count.min(FIRST) {
                println!("flooding");
                std::io::stdout().flush()?;
            }
        }
        drop(tokens);
        round += 1;
    }
    Ok(())
}
