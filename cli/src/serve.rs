//! `bwm serve`: the flags of `bwm_inference::server`.

use anyhow::Result;
use bwm_inference::server::{serve, ServeOptions};
use clap::Args;

use crate::world_model::WorldModelArgs;

#[derive(Args)]
pub struct ServeArgs {
    #[command(flatten)]
    wm: WorldModelArgs,
    #[arg(long, default_value = "127.0.0.1")]
    host: String,
    /// Port to listen on (0: any free port; the address is printed).
    #[arg(long, default_value_t = 8080)]
    port: u16,
    /// Requests that may wait while the model is busy; further ones get 503 at once.
    #[arg(long, default_value_t = 4)]
    queue: usize,
    /// Largest request body in bytes (413 above it).
    #[arg(long, default_value_t = 256 << 20)]
    max_body_bytes: usize,
    /// Open connections at most; further ones get 503 at once.
    #[arg(long, default_value_t = 512)]
    max_connections: usize,
    /// Seconds a client may take to send its request (408 after).
    #[arg(long, default_value_t = 60)]
    read_timeout_s: u64,
}

pub fn run(a: ServeArgs) -> Result<()> {
    let options = ServeOptions {
        host: a.host,
        port: a.port,
        queue: a.queue,
        max_body_bytes: a.max_body_bytes,
        max_connections: a.max_connections,
        read_timeout_s: a.read_timeout_s,
    };
    serve(&a.wm.options(), &options)
}
