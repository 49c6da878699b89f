//! Client of the openpi websocket policy protocol: the server speaks first (msgpack metadata),
//! then each binary msgpack observation gets a binary msgpack action reply; a text frame is the
//! server's traceback, followed by close 1011.
//!
//! The socket lives on its own thread, which keeps reading while the caller is busy generating
//! video so that the server's keepalive pings are answered (a silent client is dropped by the
//! `websockets` server after about 40 s).

use std::io;
use std::net::{TcpStream, ToSocketAddrs};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use rmpv::Value;
use tungstenite::protocol::WebSocketConfig;
use tungstenite::{Error as WsError, Message, WebSocket};

use crate::msgpack_numpy;

/// How long one idle read waits, and so how quickly a ping is answered.
const POLL: Duration = Duration::from_millis(100);

pub struct PolicyClient {
    requests: Option<Sender<Vec<u8>>>,
    replies: Receiver<Result<Value>>,
    worker: Option<JoinHandle<()>>,
    pub metadata: Value,
}

impl PolicyClient {
    /// Connects, completes the handshake and reads the server's metadata frame.
    pub fn connect(url: &str, timeout: Duration) -> Result<Self> {
        let rest = url
            .strip_prefix("ws://")
            .with_context(|| format!("{url}: only ws:// URLs are supported"))?;
        let authority = rest.split('/').next().unwrap_or_default();
        let addr = authority
            .to_socket_addrs()
            .with_context(|| {
                format!("{url}: cannot resolve '{authority}' (expected ws://host:port)")
            })?
            .next()
            .with_context(|| format!("{url}: '{authority}' resolves to no address"))?;
        let stream = TcpStream::connect_timeout(&addr, timeout)
            .with_context(|| format!("connecting to {url}"))?;
        stream.set_nodelay(true)?;
        stream.set_read_timeout(Some(timeout))?;
        stream.set_write_timeout(Some(timeout))?;
        let config = WebSocketConfig::default()
            .max_message_size(Some(1 << 30))
            .max_frame_size(Some(1 << 30));
        let (mut ws, _) = tungstenite::client::client_with_config(url, stream, Some(config))
            .map_err(|e| anyhow!("websocket handshake with {url} failed: {e}"))?;
        let metadata = match ws.read() {
            Ok(Message::Binary(b)) => {
                msgpack_numpy::decode(&b).context("the server's metadata frame")?
            }
            Ok(Message::Text(t)) => {
                bail!("{url}: the server sent an error instead of its metadata: {t}")
            }
            Ok(other) => bail!(
                "{url}: expected the server's metadata (a binary frame), got {}",
                describe(&other)
            ),
            Err(e) => bail!("{url}: no metadata from the server: {e}"),
        };
        ws.get_mut().set_read_timeout(Some(POLL))?;
        let (req_tx, req_rx) = mpsc::channel::<Vec<u8>>();
        let (rep_tx, rep_rx) = mpsc::channel();
        let worker = std::thread::Builder::new()
            .name("policy-socket".into())
            .spawn(move || socket_loop(ws, req_rx, rep_tx, timeout))
            .context("starting the policy socket thread")?;
        Ok(Self {
            requests: Some(req_tx),
            replies: rep_rx,
            worker: Some(worker),
            metadata,
        })
    }

    /// Sends one observation and waits for its action reply.
    pub fn infer(&mut self, obs: &Value) -> Result<Value> {
        let tx = self
            .requests
            .as_ref()
            .context("the policy connection is closed")?;
        tx.send(msgpack_numpy::encode(obs))
            .map_err(|_| anyhow!("the policy connection is closed"))?;
        self.replies
            .recv()
            .map_err(|_| anyhow!("the policy connection is closed"))?
    }
}

impl Drop for PolicyClient {
    fn drop(&mut self) {
        self.requests.take();
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

fn describe(m: &Message) -> String {
    match m {
        Message::Text(_) => "a text frame".into(),
        Message::Binary(_) => "a binary frame".into(),
        Message::Ping(_) | Message::Pong(_) => "a ping/pong".into(),
        Message::Close(f) => close_text(f.as_ref()),
        Message::Frame(_) => "a raw frame".into(),
    }
}

fn close_text(frame: Option<&tungstenite::protocol::CloseFrame>) -> String {
    match frame {
        Some(f) if f.reason.is_empty() => format!("close code {}", u16::from(f.code)),
        Some(f) => format!("close code {} ({})", u16::from(f.code), f.reason.as_str()),
        None => "close without a code".into(),
    }
}

fn would_block(e: &WsError) -> bool {
    matches!(e, WsError::Io(io) if matches!(io.kind(), io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut))
}

fn lost(e: WsError) -> anyhow::Error {
    match e {
        WsError::ConnectionClosed | WsError::AlreadyClosed => {
            anyhow!("the policy server closed the connection")
        }
        e => anyhow!("connection to the policy server lost: {e}"),
    }
}

fn socket_loop(
    mut ws: WebSocket<TcpStream>,
    requests: Receiver<Vec<u8>>,
    replies: Sender<Result<Value>>,
    timeout: Duration,
) {
    // An error seen while idle answers the next request.
    let mut broken: Option<anyhow::Error> = None;
    loop {
        match requests.recv_timeout(POLL) {
            Ok(body) => {
                let reply = match broken.take() {
                    Some(e) => Err(e),
                    None => exchange(&mut ws, body, timeout),
                };
                let failed = reply.is_err();
                if replies.send(reply).is_err() || failed {
                    break;
                }
            }
            Err(RecvTimeoutError::Timeout) => {
                if broken.is_none() {
                    broken = idle_read(&mut ws).err();
                }
            }
            Err(RecvTimeoutError::Disconnected) => break,
        }
    }
    let _ = ws.close(None);
    let _ = ws.flush();
}

/// One read while no request is outstanding: answers pings; anything else means the
/// connection is no longer usable.
fn idle_read(ws: &mut WebSocket<TcpStream>) -> Result<()> {
    match ws.read() {
        Ok(Message::Ping(_) | Message::Pong(_)) => {
            let _ = ws.flush();
            Ok(())
        }
        Ok(Message::Text(t)) => Err(anyhow!("policy server error while idle:\n{}", t.as_str())),
        Ok(Message::Close(f)) => Err(anyhow!(
            "the policy server closed the connection ({})",
            close_text(f.as_ref())
        )),
        Ok(other) => Err(anyhow!(
            "unexpected {} from the policy server while no request was pending",
            describe(&other)
        )),
        Err(e) if would_block(&e) => {
            let _ = ws.flush();
            Ok(())
        }
        Err(e) => Err(lost(e)),
    }
}

fn exchange(ws: &mut WebSocket<TcpStream>, body: Vec<u8>, timeout: Duration) -> Result<Value> {
    let deadline = Instant::now() + timeout;
    ws.send(Message::binary(body)).map_err(lost)?;
    loop {
        match ws.read() {
            Ok(Message::Binary(b)) => {
                return msgpack_numpy::decode(&b).context("the policy's reply")
            }
            Ok(Message::Text(t)) => {
                let close = wait_for_close(ws, Instant::now() + Duration::from_secs(2));
                bail!("policy server error ({close}):\n{}", t.as_str().trim_end());
            }
            Ok(Message::Close(f)) => bail!(
                "the policy server closed the connection ({})",
                close_text(f.as_ref())
            ),
            Ok(Message::Ping(_) | Message::Pong(_) | Message::Frame(_)) => {}
            Err(e) if would_block(&e) => {
                if Instant::now() > deadline {
                    bail!(
                        "no reply from the policy within {:.0} s",
                        timeout.as_secs_f64()
                    );
                }
            }
            Err(e) => return Err(lost(e)),
        }
    }
}

/// After the traceback frame openpi closes with 1011: read on until the close arrives.
fn wait_for_close(ws: &mut WebSocket<TcpStream>, deadline: Instant) -> String {
    loop {
        match ws.read() {
            Ok(Message::Close(f)) => return close_text(f.as_ref()),
            Ok(_) => {}
            Err(e) if would_block(&e) && Instant::now() < deadline => {}
            Err(e) if would_block(&e) => return "no close frame followed".into(),
            Err(WsError::ConnectionClosed) => return "connection closed".into(),
            Err(e) => return format!("then: {e}"),
        }
    }
}
