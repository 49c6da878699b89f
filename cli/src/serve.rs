//! `bwm serve`: the flags of `bwm_inference::server`.

use std::path::PathBuf;

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
    /// Largest frame in pixels, height x width (413 above it, before any work). Default: the
    /// training resolution's, where the weights record it, else 640 x 480.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    max_frame_pixels: Option<u64>,
    /// Seconds from a request's admission to its answer, queue wait included (504 after; the
    /// worker abandons the request before it starts or at its next sampler step). 0: no limit.
    #[arg(long, default_value_t = 300)]
    request_timeout_s: u64,
    /// Test hook: while this file exists, the model worker waits before each sampler step.
    #[arg(long, hide = true)]
    hold_while_exists: Option<PathBuf>,
}

pub fn run(a: ServeArgs) -> Result<()> {
    let options = ServeOptions {
        host: a.host,
        port: a.port,
        queue: a.queue,
        max_body_bytes: a.max_body_bytes,
        max_connections: a.max_connections,
        read_timeout_s: a.read_timeout_s,
        max_frame_pixels: a.max_frame_pixels.map(|n| n as usize),
        request_timeout_s: a.request_timeout_s,
        hold_while_exists: a.hold_while_exists,
    };
    serve(&a.wm.options(), &options)
}
