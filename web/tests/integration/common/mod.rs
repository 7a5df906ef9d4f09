//! What the web service's tests share.

use offworld_client::EnvClient;
use offworld_runtime::msg::Action;

/// Steps `client` with action 0 until its episode ends (bounded).
pub async fn play_to_end(client: &mut EnvClient) {
    let mut steps = 0u32;
    loop {
        let reply = client.step(Action::Discrete(0)).await.expect("step");
        steps += 1;
        if reply.terminated || reply.truncated {
            return;
        }
        assert!(steps < 10_000, "the episode never ended");
    }
}
