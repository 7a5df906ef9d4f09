//! `test_helper stops-reading`: a Zenoh client that stops reading its
//! answers and sends a burst of queries: a trainer whose laptop went to
//! sleep mid-burst, or one that means to clog the router. The first answer
//! holds the thread that reads the link (Zenoh runs a reply's callback
//! there), so none after it is read; the queries still go out. Prints
//! `sent <n>`, then stops its own process (SIGSTOP); the test kills it.
//!
//! ```text
//! test_helper stops-reading -c trainer.json5 --connect quic/127.0.0.1:7447 \
//!     --cfg 'transport/auth/usrpwd/password:"…"' --key offworld/@v1/sim/a-0/spec --count 20000
//! ```

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use offworld_program::CommonArgs;

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    common: CommonArgs,
    /// What to ask.
    #[arg(long)]
    key: String,
    /// How many queries.
    #[arg(long, default_value_t = 20_000)]
    count: u32,
    /// How long to go on after the burst before stopping, ms (the last
    /// queries leave the process).
    #[arg(long, default_value_t = 5)]
    linger_ms: u64,
}

pub async fn run(args: Args) -> anyhow::Result<()> {
    let session = args
        .common
        .client_config()
        .open()
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    // Settle first: the router has its declarations by then.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let reading = Arc::new(AtomicBool::new(true));
    for _ in 0..args.count {
        let reading = reading.clone();
        session
            .get(&args.key)
            .callback(move |_reply| {
                // The first answer: the link's reader never comes back.
                if reading.swap(false, Ordering::Relaxed) {
                    loop {
                        std::thread::park();
                    }
                }
            })
            .timeout(Duration::from_secs(60))
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    println!("sent {}", args.count);
    tokio::time::sleep(Duration::from_millis(args.linger_ms)).await;
    std::process::Command::new("kill")
        .args(["-STOP", &std::process::id().to_string()])
        .status()?;
    // Continued (nobody does): the reader stays held; the test kills this.
    tokio::time::sleep(Duration::from_secs(3600)).await;
    Ok(())
}
