//! The push path and Hub loading against a loopback HTTP server that implements the Hub calls the
//! client makes: repo creation, preupload, the git-lfs batch API (basic and multipart transfers,
//! verify), the NDJSON commit, the repo listing and `resolve/` downloads with ranges.
//!
//! Stand-in: the real Hub decides `uploadMode` from `.gitattributes` and file type; this server
//! answers `lfs` for files over 10 MiB, so the exported shards of a ~25 MiB model take the LFS path
//! and the small JSON/README files the inline one. It also answers `basic` for the first LFS object
//! of a batch and `multipart` (5 MiB parts) for the others, so both transfers run.

mod common;

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use base64::Engine;
use bwm_checkpoints::export::{export, ExportDtype, ExportOptions};
use bwm_checkpoints::hub::{cached_snapshot, push_folder, snapshot_for_loading, HubEnv, PushEvent, PushOptions};
use bwm_checkpoints::open::open_local;
use bwm_model::{DitConfig, ModelConfig};
use common::*;
use sha2::{Digest, Sha256};
use tiny_http::{Header, Response, Server};

const TOKEN: &str = "hf_test_write_token";
const REPO: &str = "me/bwm-test";
const LFS_THRESHOLD: usize = 10 << 20;
const PART: usize = 5 << 20;
const COMMIT: &str = "0123456789abcdef0123456789abcdef01234567";

#[derive(Default)]
struct HubState {
    created: Vec<(String, bool)>,
    /// Committed files: path -> bytes.
    files: BTreeMap<String, Vec<u8>>,
    lfs: BTreeMap<String, Vec<u8>>,
    parts: BTreeMap<(String, u64), Vec<u8>>,
    transfers: Vec<String>,
    verified: Vec<String>,
    commits: usize,
    calls: Vec<String>,
}

fn sha(b: &[u8]) -> String {
    Sha256::digest(b).iter().map(|x| format!("{x:02x}")).collect()
}

struct Loopback {
    url: String,
    state: Arc<Mutex<HubState>>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for Loopback {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn json(v: serde_json::Value) -> Response<std::io::Cursor<Vec<u8>>> {
    Response::from_string(v.to_string()).with_header(Header::from_bytes("Content-Type", "application/json").unwrap())
}

fn serve() -> Loopback {
    let server = Server::http("127.0.0.1:0").unwrap();
    let url = format!("http://{}", server.server_addr().to_ip().unwrap());
    let state = Arc::new(Mutex::new(HubState::default()));
    let stop = Arc::new(AtomicBool::new(false));
    let (st, sp, base) = (state.clone(), stop.clone(), url.clone());
    // Bounded: the loop ends when the test drops the server handle (or after 10 minutes).
    let thread = std::thread::spawn(move || {
        let started = std::time::Instant::now();
        while !sp.load(Ordering::SeqCst) && started.elapsed() < Duration::from_secs(600) {
            let Ok(Some(mut req)) = server.recv_timeout(Duration::from_millis(50)) else { continue };
            let method = req.method().to_string();
            let path = req.url().split('?').next().unwrap_or("").to_string();
            let header = |name: &str| req.headers().iter().find(|h| h.field.as_str().as_str().eq_ignore_ascii_case(name)).map(|h| h.value.as_str().to_string());
            let auth = header("Authorization");
            let range = header("Range");
            let mut body = Vec::new();
            req.as_reader().read_to_end(&mut body).unwrap();
            let mut s = st.lock().unwrap();
            s.calls.push(format!("{method} {path}"));
            let authed = auth.as_deref() == Some(&format!("Bearer {TOKEN}"));
            let api = format!("/api/models/{REPO}");
            let resp = if (path.starts_with("/api/") || path.contains(".git/")) && method == "POST" && !authed {
                json(serde_json::json!({"error": "Invalid credentials in Authorization header"})).with_status_code(401)
            } else if method == "POST" && path == "/api/repos/create" {
                let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
                let name = format!("{}/{}", v["organization"].as_str().unwrap(), v["name"].as_str().unwrap());
                let exists = s.created.iter().any(|(n, _)| *n == name);
                if exists {
                    json(serde_json::json!({"error": "You already created this model repo"})).with_status_code(409)
                } else {
                    s.created.push((name.clone(), v["private"].as_bool().unwrap_or(false)));
                    json(serde_json::json!({"url": format!("{base}/{name}")}))
                }
            } else if method == "POST" && path == format!("{api}/preupload/main") {
                let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
                let files: Vec<serde_json::Value> = v["files"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|f| {
                        let lfs = f["size"].as_u64().unwrap() as usize > LFS_THRESHOLD;
                        serde_json::json!({"path": f["path"], "uploadMode": if lfs { "lfs" } else { "regular" }, "shouldIgnore": false})
                    })
                    .collect();
                json(serde_json::json!({"files": files}))
            } else if method == "POST" && path == format!("/{REPO}.git/info/lfs/objects/batch") {
                let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
                assert_eq!(v["operation"], "upload");
                let mut objects = Vec::new();
                for (i, o) in v["objects"].as_array().unwrap().iter().enumerate() {
                    let oid = o["oid"].as_str().unwrap().to_string();
                    let size = o["size"].as_u64().unwrap() as usize;
                    if s.lfs.contains_key(&oid) {
                        objects.push(serde_json::json!({"oid": oid, "size": size}));
                        continue;
                    }
                    let verify = serde_json::json!({"href": format!("{base}/lfs-verify/{oid}"), "header": {"X-Verify": "1"}});
                    if i == 0 {
                        s.transfers.push("basic".into());
                        objects.push(serde_json::json!({"oid": oid, "size": size, "actions": {
                            "upload": {"href": format!("{base}/lfs-put/{oid}"), "header": {"X-Upload": "basic"}}, "verify": verify}}));
                    } else {
                        s.transfers.push("multipart".into());
                        let mut h = serde_json::Map::new();
                        h.insert("chunk_size".into(), PART.to_string().into());
                        for p in 1..=size.div_ceil(PART) {
                            h.insert(p.to_string(), format!("{base}/lfs-part/{oid}/{p}").into());
                        }
                        objects.push(serde_json::json!({"oid": oid, "size": size, "actions": {
                            "upload": {"href": format!("{base}/lfs-complete/{oid}"), "header": h}, "verify": verify}}));
                    }
                }
                json(serde_json::json!({"transfer": "basic", "objects": objects}))
            } else if method == "PUT" && path.starts_with("/lfs-put/") {
                let oid = path.trim_start_matches("/lfs-put/").to_string();
                assert!(auth.is_none(), "no Hub token is sent to the storage URL");
                assert_eq!(sha(&body), oid, "basic upload body matches its oid");
                s.lfs.insert(oid, body);
                Response::from_string("")
            } else if method == "PUT" && path.starts_with("/lfs-part/") {
                let rest: Vec<&str> = path.trim_start_matches("/lfs-part/").split('/').collect();
                let n: u64 = rest[1].parse().unwrap();
                s.parts.insert((rest[0].to_string(), n), body);
                Response::from_string("").with_header(Header::from_bytes("ETag", format!("\"etag-{n}\"")).unwrap())
            } else if method == "POST" && path.starts_with("/lfs-complete/") {
                let oid = path.trim_start_matches("/lfs-complete/").to_string();
                let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
                assert_eq!(v["oid"], oid.as_str());
                let mut all = Vec::new();
                for (i, p) in v["parts"].as_array().unwrap().iter().enumerate() {
                    let n = p["partNumber"].as_u64().unwrap();
                    assert_eq!(n, i as u64 + 1);
                    assert_eq!(p["etag"], format!("\"etag-{n}\""));
                    all.extend_from_slice(&s.parts[&(oid.clone(), n)]);
                }
                assert_eq!(sha(&all), oid, "multipart parts reassemble to the object");
                s.lfs.insert(oid, all);
                json(serde_json::json!({}))
            } else if method == "POST" && path.starts_with("/lfs-verify/") {
                let oid = path.trim_start_matches("/lfs-verify/").to_string();
                if s.lfs.contains_key(&oid) {
                    s.verified.push(oid);
                    json(serde_json::json!({}))
                } else {
                    json(serde_json::json!({"message": "object not found"})).with_status_code(404)
                }
            } else if method == "POST" && path == format!("{api}/commit/main") {
                let text = String::from_utf8(body).unwrap();
                let mut lines = text.lines();
                let header: serde_json::Value = serde_json::from_str(lines.next().unwrap()).unwrap();
                assert_eq!(header["key"], "header");
                let mut ok = true;
                for l in lines {
                    let v: serde_json::Value = serde_json::from_str(l).unwrap();
                    let p = v["value"]["path"].as_str().unwrap().to_string();
                    match v["key"].as_str().unwrap() {
                        "file" => {
                            let bytes = base64::engine::general_purpose::STANDARD.decode(v["value"]["content"].as_str().unwrap()).unwrap();
                            ok &= bytes.len() <= LFS_THRESHOLD;
                            s.files.insert(p, bytes);
                        }
                        "lfsFile" => {
                            let oid = v["value"]["oid"].as_str().unwrap();
                            match s.lfs.get(oid).cloned() {
                                Some(b) if b.len() as u64 == v["value"]["size"].as_u64().unwrap() => {
                                    s.files.insert(p, b);
                                }
                                _ => ok = false,
                            }
                        }
                        "deletedFile" => {
                            s.files.remove(&p);
                        }
                        other => panic!("unexpected commit line {other}"),
                    }
                }
                if ok {
                    s.commits += 1;
                    json(serde_json::json!({"commitUrl": format!("{base}/{REPO}/commit/{COMMIT}"), "commitOid": COMMIT}))
                } else {
                    json(serde_json::json!({"error": "an lfsFile was not uploaded, or a regular file is over 10 MiB"})).with_status_code(422)
                }
            } else if method == "GET" && path == api && authed {
                let private = s.created.iter().find(|(n, _)| n == REPO).map(|(_, p)| *p);
                match private {
                    Some(p) => json(serde_json::json!({"id": REPO, "private": p})),
                    None => json(serde_json::json!({"error": "Repository not found"})).with_status_code(404),
                }
            } else if method == "GET" && path == format!("{api}/revision/main") {
                let siblings: Vec<serde_json::Value> = s.files.keys().map(|k| serde_json::json!({"rfilename": k})).collect();
                json(serde_json::json!({"sha": COMMIT, "siblings": siblings}))
            } else if method == "GET" && path.starts_with(&format!("/{REPO}/resolve/main/")) {
                let file = path.trim_start_matches(&format!("/{REPO}/resolve/main/")).to_string();
                match s.files.get(&file) {
                    Some(b) => {
                        let total = b.len();
                        let (start, end) = match range.as_deref().and_then(|r| r.strip_prefix("bytes=")) {
                            Some(r) => {
                                let (a, z) = r.split_once('-').unwrap();
                                let a: usize = a.parse().unwrap();
                                let z: usize = if z.is_empty() { total.saturating_sub(1) } else { z.parse().unwrap() };
                                (a, z.min(total.saturating_sub(1)))
                            }
                            None => (0, total.saturating_sub(1)),
                        };
                        let slice = if total == 0 { Vec::new() } else { b[start..=end].to_vec() };
                        Response::from_data(slice)
                            .with_status_code(206)
                            .with_header(Header::from_bytes("Content-Range", format!("bytes {start}-{end}/{total}")).unwrap())
                            .with_header(Header::from_bytes("ETag", format!("\"{}\"", sha(b))).unwrap())
                            .with_header(Header::from_bytes("X-Repo-Commit", COMMIT).unwrap())
                    }
                    None => json(serde_json::json!({"error": "Entry not found"})).with_status_code(404),
                }
            } else {
                json(serde_json::json!({"error": format!("not implemented: {method} {path}")})).with_status_code(501)
            };
            drop(s);
            let _ = req.respond(resp);
        }
    });
    Loopback { url, state, stop, thread: Some(thread) }
}

/// A model of ~25 MiB in fp32, so that 12 MiB shards exceed the 10 MiB LFS threshold.
fn mid_model() -> ModelConfig {
    let dit = DitConfig { dim: 256, ffn_dim: 1024, num_heads: 2, num_layers: 6, ..DitConfig::tiny() };
    ModelConfig { dit, action: Default::default() }
}

fn env_for(url: &str, home: &std::path::Path, offline: bool) -> HubEnv {
    HubEnv { endpoint: url.to_string(), token: Some(TOKEN.into()), hf_home: home.to_path_buf(), offline, progress: false }
}

#[test]
fn push_uploads_lfs_and_regular_files_then_the_repo_loads_from_the_cache() {
    let root = tmp_dir("push");
    let cfg = mid_model();
    let model = random_model(&cfg, 21);
    let ckpt = fake_run(&root, &model, &|c| {
        run_toml("push", "tiny", Some("dim = 256\nin_dim = 48\nout_dim = 48\nffn_dim = 1024\nfreq_dim = 256\ntext_dim = 64\nnum_heads = 2\nnum_layers = 6\neps = 1e-6\npatch_size = [1, 2, 2]"), c)
    });
    let out = root.join("export");
    let opts = ExportOptions { dtype: ExportDtype::F32, shard_size: 12 << 20, repo_id: Some(REPO.into()), ..Default::default() };
    let rep = export(ckpt.to_str().unwrap(), &out, &opts, &mut |_| {}).unwrap();
    let big: Vec<&str> = rep.files.iter().filter(|f| f.bytes as usize > LFS_THRESHOLD).map(|f| f.path.as_str()).collect();
    assert!(big.len() >= 2, "at least two shards over 10 MiB: {:?}", rep.files);

    let server = serve();
    let home = root.join("hf-home");
    let env = env_for(&server.url, &home, false);
    let mut events = Vec::new();
    let push = PushOptions::new(REPO, true, &env);
    let report = push_folder(&out, &push, &mut |e| events.push(e.clone())).unwrap();
    {
        let s = server.state.lock().unwrap();
        assert_eq!(s.created, vec![(REPO.to_string(), true)], "created private");
        assert_eq!(s.commits, 1);
        assert_eq!(report.lfs_files, big.len());
        assert!(report.regular_files >= 3, "config, index, README at least");
        assert!(s.transfers.contains(&"basic".to_string()) && s.transfers.contains(&"multipart".to_string()), "{:?}", s.transfers);
        assert_eq!(s.verified.len(), big.len());
        // Every local file arrived byte-identical.
        for f in &rep.files {
            let local = std::fs::read(out.join(&f.path)).unwrap();
            assert_eq!(s.files.get(&f.path).map(|b| sha(b)), Some(sha(&local)), "{}", f.path);
        }
        assert_eq!(s.files.len(), rep.files.len());
    }
    assert!(events.iter().any(|e| matches!(e, PushEvent::Uploading { sent, total, .. } if sent == total)), "progress reported");
    assert_eq!(report.commit_oid.as_deref(), Some(COMMIT));

    // Pushing again: the repo exists (409 is fine) and the LFS objects are already stored; a
    // file of an earlier push that this folder lacks (a shard of another layout) is deleted, the
    // Hub's .gitattributes kept.
    for stale in ["old-layout-00001-of-00002.safetensors", ".gitattributes"] {
        server.state.lock().unwrap().files.insert(stale.into(), b"x".to_vec());
    }
    let again = push_folder(&out, &push, &mut |_| {}).unwrap();
    assert_eq!(again.lfs_skipped, big.len());
    assert_eq!(again.deleted, ["old-layout-00001-of-00002.safetensors"]);
    {
        let s = server.state.lock().unwrap();
        assert!(!s.files.contains_key("old-layout-00001-of-00002.safetensors") && s.files.contains_key(".gitattributes"));
    }
    server.state.lock().unwrap().files.remove(".gitattributes");
    // A private push into a repo that exists and is public is refused before anything is sent.
    server.state.lock().unwrap().created[0].1 = false;
    let commits = server.state.lock().unwrap().commits;
    let e = push_folder(&out, &push, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("exists and is public: --private would publish"), "{e}");
    assert_eq!(server.state.lock().unwrap().commits, commits);
    server.state.lock().unwrap().created[0].1 = true;

    // A refused token is a clear error.
    let bad = PushOptions { token: Some("hf_wrong".into()), ..push.clone() };
    let e = push_folder(&out, &bad, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("401") && e.contains("token"), "{e}");
    // No token at all.
    let none = PushOptions { token: None, ..push.clone() };
    let e = push_folder(&out, &none, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("HF_TOKEN"), "{e}");

    // Loading by repo id: downloads through hf-hub into HF_HOME/hub, then reads the snapshot.
    let snap = snapshot_for_loading(REPO, &env).unwrap();
    assert!(snap.starts_with(home.join("hub")), "{}", snap.display());
    let opened = open_local(&snap).unwrap();
    assert_eq!(opened.config.as_ref(), Some(&cfg));
    let want: BTreeMap<String, tch::Tensor> = params(&model).into_iter().filter(|(n, _)| !n.starts_with("text_embedding.")).collect();
    assert_same(&read_all(&opened), &want, tch::Kind::Float, "from the Hub");
    assert!(!server.state.lock().unwrap().calls.iter().any(|c| c.contains("README")), "only what loading needs is downloaded");

    // Offline: the server is gone, the cache alone serves the repo.
    drop(server);
    let offline = env_for("http://127.0.0.1:9", &home, true);
    let snap2 = snapshot_for_loading(REPO, &offline).unwrap();
    assert_eq!(snap2, snap);
    assert_eq!(cached_snapshot(&offline, REPO, "main"), Some(snap.clone()));
    assert_same(&read_all(&open_local(&snap2).unwrap()), &want, tch::Kind::Float, "offline");
    let e = snapshot_for_loading("me/not-cached", &offline).unwrap_err().to_string();
    assert!(e.contains("HF_HUB_OFFLINE") && e.contains("me/not-cached"), "{e}");
}
