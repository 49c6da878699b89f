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
use tungstenite::handshake::HandshakeError;
use tungstenite::protocol::WebSocketConfig;
use tungstenite::{Error as WsError, Message, WebSocket};

use crate::msgpack_numpy;

/// How long one idle read waits, and so how quickly a ping is answered.
const POLL: Duration = Duration::from_millis(100);

/// A failure of the connection to the policy server itself (reaching it, its handshake and
/// metadata, the connection lost or closed), as opposed to the policy's own (an error reply, a bad
/// or late reply).
#[derive(Debug)]
pub struct ConnectionError(pub String);

impl std::fmt::Display for ConnectionError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for ConnectionError {}

fn connection(message: impl Into<String>) -> anyhow::Error {
    ConnectionError(message.into()).into()
}

/// Seconds as people write them: 1, 0.5.
fn seconds(d: Duration) -> String {
    format!("{}", d.as_secs_f64())
}

pub struct PolicyClient {
    requests: Option<Sender<Vec<u8>>>,
    replies: Receiver<Result<Value>>,
    worker: Option<JoinHandle<()>>,
    pub metadata: Value,
}

impl PolicyClient {
    /// Connects, completes the handshake and reads the server's metadata frame, each within
    /// `timeout`; every failure here is a [`ConnectionError`].
    pub fn connect(url: &str, timeout: Duration) -> Result<Self> {
        let rest = url.strip_prefix("ws://").ok_or_else(|| connection(format!("{url}: only ws:// URLs are supported")))?;
        let authority = rest.split('/').next().unwrap_or_default();
        let addr = authority
            .to_socket_addrs()
            .map_err(|e| connection(format!("{url}: cannot resolve '{authority}' (expected ws://host:port): {e}")))?
            .next()
            .ok_or_else(|| connection(format!("{url}: '{authority}' resolves to no address")))?;
        let stream = TcpStream::connect_timeout(&addr, timeout).map_err(|e| connection(format!("connecting to {url}: {e}")))?;
        let setup = |stream: &TcpStream| -> io::Result<()> {
            stream.set_nodelay(true)?;
            stream.set_read_timeout(Some(timeout))?;
            stream.set_write_timeout(Some(timeout))
        };
        setup(&stream).map_err(|e| connection(format!("{url}: {e}")))?;
        let config = WebSocketConfig::default()
            .max_message_size(Some(1 << 30))
            .max_frame_size(Some(1 << 30));
        let mut ws = match tungstenite::client::client_with_config(url, stream, Some(config)) {
            Ok((ws, _)) => ws,
            // The blocking socket's read timeout surfaces as an interrupted (would-block) handshake.
            Err(HandshakeError::Interrupted(_)) => {
                return Err(connection(format!("{url}: the policy server did not answer the websocket handshake within {} s", seconds(timeout))))
            }
            Err(HandshakeError::Failure(e)) if would_block(&e) => {
                return Err(connection(format!("{url}: the policy server did not answer the websocket handshake within {} s", seconds(timeout))))
            }
            Err(HandshakeError::Failure(e)) => return Err(connection(format!("websocket handshake with {url} failed: {e}"))),
        };
        let metadata = match ws.read() {
            Ok(Message::Binary(b)) => {
                msgpack_numpy::decode(&b).context("the server's metadata frame")?
            }
            Ok(Message::Text(t)) => {
                bail!("{url}: the server sent an error instead of its metadata: {t}")
            }
            Ok(other) => {
                return Err(connection(format!("{url}: expected the server's metadata (a binary frame), got {}", describe(&other))))
            }
            Err(e) if would_block(&e) => return Err(connection(format!("{url}: the policy server sent no metadata within {} s", seconds(timeout)))),
            Err(e) => return Err(connection(format!("{url}: no metadata from the server: {e}"))),
        };
        ws.get_mut().set_read_timeout(Some(POLL)).map_err(|e| connection(format!("{url}: {e}")))?;
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
        let tx = self.requests.as_ref().ok_or_else(|| connection("the policy connection is closed"))?;
        tx.send(msgpack_numpy::encode(obs)).map_err(|_| connection("the policy connection is closed"))?;
        self.replies.recv().map_err(|_| connection("the policy connection is closed"))?
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
        WsError::ConnectionClosed | WsError::AlreadyClosed => connection("the policy server closed the connection"),
        e => connection(format!("connection to the policy server lost: {e}")),
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
        Ok(Message::Close(f)) => Err(connection(format!("the policy server closed the connection ({})", close_text(f.as_ref())))),
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
            Ok(Message::Close(f)) => return Err(connection(format!("the policy server closed the connection ({})", close_text(f.as_ref())))),
            Ok(Message::Ping(_) | Message::Pong(_) | Message::Frame(_)) => {}
            Err(e) if would_block(&e) => {
                if Instant::now() > deadline {
                    bail!("no reply from the policy within {} s", seconds(timeout));
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::TcpListener;

    /// Runs `serve` on the one connection a local listener accepts; returns its URL and a sender
    /// whose drop ends the server.
    fn server(serve: impl FnOnce(TcpStream, Receiver<()>) + Send + 'static) -> (String, Sender<()>, JoinHandle<()>) {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("ws://{}", listener.local_addr().unwrap());
        let (stop, stopped) = mpsc::channel();
        let thread = std::thread::spawn(move || {
            let (stream, _) = listener.accept().unwrap();
            serve(stream, stopped);
        });
        (url, stop, thread)
    }

    #[test]
    fn a_server_that_sends_no_metadata_is_named_by_the_timeout() {
        let (url, stop, thread) = server(|stream, stopped| {
            let _ws = tungstenite::accept(stream).unwrap();
            let _ = stopped.recv();
        });
        let err = PolicyClient::connect(&url, Duration::from_secs(1)).err().expect("no metadata: no client");
        assert!(err.is::<ConnectionError>(), "{err:#}");
        let e = format!("{err:#}");
        assert!(e.contains("policy server sent no metadata within 1 s"), "{e}");
        assert!(!e.contains("os error"), "{e}");
        drop(stop);
        thread.join().unwrap();
    }

    #[test]
    fn a_server_that_never_answers_the_handshake_is_named_by_the_timeout() {
        let (url, stop, thread) = server(|_stream, stopped| {
            let _ = stopped.recv();
        });
        let e = format!("{:#}", PolicyClient::connect(&url, Duration::from_secs(1)).err().expect("no handshake: no client"));
        assert!(e.contains("did not answer the websocket handshake within 1 s"), "{e}");
        assert!(!e.contains("os error"), "{e}");
        drop(stop);
        thread.join().unwrap();
    }
}
