//! The Hugging Face Hub: reading repos through hf-hub's cache, and pushing an exported folder.
//!
//! **Downloads** use the `hf-hub` crate (pinned `=0.4.3`, sync API over ureq): its cache layout
//! (`$HF_HOME/hub/models--owner--name/{refs,snapshots,blobs}`), shared with the Python
//! `huggingface_hub`, so a cache filled by either works here. `HF_HUB_OFFLINE=1` reads only the
//! cache (hf-hub 0.4.3 itself ignores that variable; it is honoured here).
//!
//! **Uploads**: hf-hub 0.4.3 has no upload API. hf-hub 1.0.0 has one (`create_commit`,
//! `upload_folder`), but it moves large files only through Xet: when the Hub's LFS batch answer
//! does not choose the `xet` transfer, its LFS files fall back to inline base64 in the commit,
//! which the Hub refuses for large files, and it brings the whole hf-xet stack with it. So the
//! push implements the Hub's HTTP commit protocol directly with `ureq` (the HTTP client hf-hub
//! 0.4.3 itself uses), as `huggingface_hub` does without hf_xet:
//!
//! 1. `POST {endpoint}/api/repos/create` (`{"name", "organization", "private"}`; 409 = exists);
//! 2. `POST {endpoint}/api/models/{repo}/preupload/{rev}`: per file `{path, size, sample}` ->
//!    `uploadMode` `lfs` or `regular`;
//! 3. for LFS files, `POST {endpoint}/{repo}.git/info/lfs/objects/batch` (git-lfs batch API,
//!    transfers `basic` and `multipart`, sha256 oids), then per object either one `PUT` to the
//!    `upload` href, or (multipart: `chunk_size` and numbered part URLs in the action header) a
//!    `PUT` per part and a `POST` of `{oid, parts: [{partNumber, etag}]}` to the href; then the
//!    `verify` action when given; objects without actions are already stored;
//! 4. `POST {endpoint}/api/models/{repo}/commit/{rev}` (NDJSON: a header line, `file` lines with
//!    base64 content for regular files, `lfsFile` lines `{path, algo: sha256, oid, size}`).

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, ensure, Context, Result};
use base64::Engine;
use sha2::{Digest, Sha256};

pub const DEFAULT_ENDPOINT: &str = "https://huggingface.co";

/// The Hub settings from the environment.
#[derive(Debug, Clone, Default)]
pub struct HubEnv {
    /// `HF_ENDPOINT`, default `https://huggingface.co`.
    pub endpoint: String,
    /// `HF_TOKEN`, else the token file `$HF_HOME/token` that `hf auth login` writes.
    pub token: Option<String>,
    /// `HF_HOME` (default `~/.cache/huggingface`); the cache is its `hub/` folder.
    pub hf_home: PathBuf,
    /// `HF_HUB_OFFLINE` set to 1/true/yes/on.
    pub offline: bool,
    /// Progress bars for downloads.
    pub progress: bool,
}

impl HubEnv {
    pub fn from_env() -> Self {
        let var = |k: &str| std::env::var(k).ok().filter(|v| !v.trim().is_empty());
        let hf_home = var("HF_HOME").map(PathBuf::from).unwrap_or_else(|| {
            let home = var("HOME").unwrap_or_else(|| ".".into());
            Path::new(&home).join(".cache").join("huggingface")
        });
        let file_token = std::fs::read_to_string(hf_home.join("token")).ok().map(|t| t.trim().to_string()).filter(|t| !t.is_empty());
        Self {
            endpoint: var("HF_ENDPOINT").unwrap_or_else(|| DEFAULT_ENDPOINT.into()).trim_end_matches('/').to_string(),
            token: var("HF_TOKEN").map(|t| t.trim().to_string()).or(file_token),
            offline: var("HF_HUB_OFFLINE").is_some_and(|v| matches!(v.trim().to_ascii_lowercase().as_str(), "1" | "true" | "yes" | "on")),
            hf_home,
            progress: std::io::IsTerminal::is_terminal(&std::io::stderr()),
        }
    }

    pub fn cache_dir(&self) -> PathBuf {
        self.hf_home.join("hub")
    }
}

fn split_revision(spec: &str) -> (String, String) {
    match spec.split_once('@') {
        Some((id, rev)) if !rev.is_empty() => (id.to_string(), rev.to_string()),
        _ => (spec.trim_end_matches('@').to_string(), "main".to_string()),
    }
}

/// The cached snapshot folder of `repo_id` at `revision` (a branch/tag through `refs/`, or a
/// commit hash), when the cache has it.
pub fn cached_snapshot(env: &HubEnv, repo_id: &str, revision: &str) -> Option<PathBuf> {
    let repo = hf_hub::Repo::with_revision(repo_id.to_string(), hf_hub::RepoType::Model, revision.to_string());
    let base = env.cache_dir().join(repo.folder_name());
    let commit = match std::fs::read_to_string(base.join("refs").join(revision)) {
        Ok(c) => c.trim().to_string(),
        Err(_) if revision.len() == 40 && revision.chars().all(|c| c.is_ascii_hexdigit()) => revision.to_string(),
        Err(_) => return None,
    };
    let snap = base.join("snapshots").join(commit);
    snap.is_dir().then_some(snap)
}

/// Files of a repo listing that loading the DiT needs: configs, shard indexes, `action_stats.json`,
/// and the weights of the root, `transformer/` and `action_encoder/` (the shards an index lists, or
/// the `.safetensors` files of a component without one). Not the VAE, text encoder or tokenizer.
fn wanted_files(listing: &[String], read_index: &mut dyn FnMut(&str) -> Result<Vec<String>>) -> Result<Vec<String>> {
    let mut out = Vec::new();
    for comp in ["", "transformer/", "action_encoder/"] {
        let here: Vec<&String> = listing
            .iter()
            .filter(|f| f.starts_with(comp) && !f[comp.len()..].contains('/'))
            .collect();
        for f in &here {
            let name = &f[comp.len()..];
            if name == "config.json" || (comp.is_empty() && name == crate::repo::ACTION_STATS_FILE) {
                out.push(f.to_string());
            }
        }
        let indexes: Vec<&&String> = here.iter().filter(|f| f.ends_with(".safetensors.index.json")).collect();
        if let Some(index) = indexes.first() {
            out.push(index.to_string());
            for shard in read_index(index)? {
                let path = format!("{comp}{shard}");
                if !out.contains(&path) {
                    out.push(path);
                }
            }
        } else {
            out.extend(here.iter().filter(|f| f.ends_with(".safetensors")).map(|f| f.to_string()));
        }
    }
    Ok(out)
}

/// A local snapshot folder holding what loading `spec` (`owner/name[@revision]`) needs: from the
/// cache alone when offline, else downloaded into the cache (files already there are reused).
pub fn snapshot_for_loading(spec: &str, env: &HubEnv) -> Result<PathBuf> {
    let (repo_id, revision) = split_revision(spec);
    if env.offline {
        return cached_snapshot(env, &repo_id, &revision).with_context(|| {
            format!(
                "HF_HUB_OFFLINE is set and the Hugging Face cache ({}) has no snapshot of {repo_id} at '{revision}'; download it first (unset HF_HUB_OFFLINE)",
                env.cache_dir().display()
            )
        });
    }
    let api = hf_hub::api::sync::ApiBuilder::from_cache(hf_hub::Cache::new(env.cache_dir()))
        .with_endpoint(env.endpoint.clone())
        .with_token(env.token.clone())
        .with_progress(env.progress)
        .build()
        .context("setting up the Hub client")?;
    let repo = api.repo(hf_hub::Repo::with_revision(repo_id.clone(), hf_hub::RepoType::Model, revision.clone()));
    let info = match repo.info() {
        Ok(info) => info,
        Err(e) => {
            if let Some(snap) = cached_snapshot(env, &repo_id, &revision) {
                eprintln!("warning: cannot reach {} ({e}); using the cached snapshot {}", env.endpoint, snap.display());
                return Ok(snap);
            }
            bail!("cannot list {repo_id} at '{revision}' on {}: {e} (with no network, fill the cache first and set HF_HUB_OFFLINE=1)", env.endpoint);
        }
    };
    let listing: Vec<String> = info.siblings.iter().map(|s| s.rfilename.clone()).collect();
    let get = |file: &str| -> Result<PathBuf> {
        repo.get(file).with_context(|| format!("downloading {file} of {repo_id} from {}", env.endpoint))
    };
    let mut first: Option<(String, PathBuf)> = None;
    let mut read_index = |index: &str| -> Result<Vec<String>> {
        let path = get(index)?;
        let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
        let v: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{index}: not JSON"))?;
        let map = v.get("weight_map").and_then(|m| m.as_object()).with_context(|| format!("{index}: no weight_map"))?;
        let mut shards: Vec<String> = map.values().filter_map(|f| f.as_str().map(String::from)).collect();
        shards.sort();
        shards.dedup();
        Ok(shards)
    };
    let files = wanted_files(&listing, &mut read_index)?;
    ensure!(!files.is_empty(), "{repo_id} at '{revision}' holds no DiT weights this loader knows (no .safetensors at the root, in transformer/ or action_encoder/)");
    for f in &files {
        let path = get(f)?;
        if first.is_none() {
            first = Some((f.clone(), path));
        }
    }
    let (file, path) = first.context("nothing downloaded")?;
    // snapshots/<commit>/<file>: strip the file's own components.
    let mut snap = path;
    for _ in file.split('/') {
        snap.pop();
    }
    Ok(snap)
}

/// What `push_folder` does.
#[derive(Debug, Clone)]
pub struct PushOptions {
    /// `owner/name`.
    pub repo_id: String,
    /// Create the repo private (an existing repo keeps its visibility).
    pub private: bool,
    pub endpoint: String,
    pub token: Option<String>,
    pub revision: String,
    pub commit_message: String,
}

impl PushOptions {
    pub fn new(repo_id: &str, private: bool, env: &HubEnv) -> Self {
        Self {
            repo_id: repo_id.to_string(),
            private,
            endpoint: env.endpoint.clone(),
            token: env.token.clone(),
            revision: "main".into(),
            commit_message: "Upload BWM world model export".into(),
        }
    }
}

/// Progress of a push.
#[derive(Debug, Clone, PartialEq)]
pub enum PushEvent {
    RepoReady { url: String, created: bool },
    Hashed { path: String, bytes: u64 },
    /// Bytes of one LFS file sent so far.
    Uploading { path: String, sent: u64, total: u64 },
    AlreadyOnHub { path: String },
    /// Files the repo holds and the folder does not, deleted by the commit.
    Deleting { paths: Vec<String> },
    Committing { files: usize },
}

#[derive(Debug, Clone, PartialEq)]
pub struct PushReport {
    pub repo_url: String,
    pub commit_url: Option<String>,
    pub commit_oid: Option<String>,
    pub lfs_files: usize,
    pub regular_files: usize,
    /// LFS files the Hub already had (no upload).
    pub lfs_skipped: usize,
    /// Files of an earlier push that the folder does not hold, deleted (a stale shard or index
    /// of another layout would otherwise sit beside the new weights).
    pub deleted: Vec<String>,
}

struct LocalFile {
    path: PathBuf,
    rel: String,
    size: u64,
    sha256: String,
    sample: Vec<u8>,
}

fn collect_files(root: &Path, dir: &Path, out: &mut Vec<(PathBuf, String)>) -> Result<()> {
    let mut entries: Vec<_> = std::fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))?.collect::<Result<_, _>>()?;
    entries.sort_by_key(|e| e.file_name());
    for e in entries {
        let name = e.file_name().to_string_lossy().to_string();
        if name.starts_with('.') {
            continue;
        }
        let path = e.path();
        if path.is_dir() {
            collect_files(root, &path, out)?;
        } else {
            let rel = path.strip_prefix(root).unwrap_or(&path).components().map(|c| c.as_os_str().to_string_lossy()).collect::<Vec<_>>().join("/");
            out.push((path, rel));
        }
    }
    Ok(())
}

fn hash_file(path: &Path) -> Result<(u64, String, Vec<u8>)> {
    let mut f = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 8 << 20];
    let mut size = 0u64;
    let mut sample = Vec::new();
    loop {
        let n = f.read(&mut buf).with_context(|| format!("reading {}", path.display()))?;
        if n == 0 {
            break;
        }
        if sample.len() < 512 {
            let take = (512 - sample.len()).min(n);
            sample.extend_from_slice(&buf[..take]);
        }
        hasher.update(&buf[..n]);
        size += n as u64;
    }
    let sha: String = hasher.finalize().iter().map(|b| format!("{b:02x}")).collect();
    Ok((size, sha, sample))
}

fn agent() -> ureq::Agent {
    ureq::AgentBuilder::new()
        .try_proxy_from_env(true)
        .timeout_connect(Duration::from_secs(30))
        .timeout_read(Duration::from_secs(600))
        .build()
}

/// A one-line error from a failed Hub call: the status and what the server said.
fn call_error(what: &str, err: ureq::Error) -> anyhow::Error {
    match err {
        ureq::Error::Status(code, resp) => {
            let url = resp.get_url().to_string();
            let body = resp.into_string().unwrap_or_default();
            let said = serde_json::from_str::<serde_json::Value>(&body)
                .ok()
                .and_then(|v| v.get("error").and_then(|e| e.as_str()).map(String::from))
                .unwrap_or_else(|| body.chars().take(300).collect());
            let hint = match code {
                401 => " (the token was refused: HF_TOKEN must be a valid token)",
                403 => " (the token lacks write access to this namespace)",
                404 => " (no such repo or revision)",
                _ => "",
            };
            anyhow::anyhow!("{what}: HTTP {code} from {url}{hint}: {}", said.trim())
        }
        ureq::Error::Transport(t) => anyhow::anyhow!("{what}: {t}"),
    }
}

struct Hub<'a> {
    opts: &'a PushOptions,
    token: String,
    agent: ureq::Agent,
}

impl Hub<'_> {
    fn auth(&self, req: ureq::Request) -> ureq::Request {
        req.set("Authorization", &format!("Bearer {}", self.token)).set("User-Agent", concat!("bwm/", env!("CARGO_PKG_VERSION")))
    }

    fn post_json(&self, url: &str, body: &serde_json::Value, what: &str) -> Result<ureq::Response> {
        self.auth(self.agent.post(url))
            .set("Content-Type", "application/json")
            .send_string(&body.to_string())
            .map_err(|e| call_error(what, e))
    }

    fn json(resp: ureq::Response, what: &str) -> Result<serde_json::Value> {
        let text = resp.into_string().with_context(|| format!("{what}: reading the answer"))?;
        serde_json::from_str(&text).with_context(|| format!("{what}: the answer is not JSON: {}", text.chars().take(200).collect::<String>()))
    }

    /// Creates the repo; an existing one is fine, unless the push asks for a private repo and it
    /// is public (the weights would be published).
    fn create_repo(&self) -> Result<bool> {
        let (owner, name) = self.opts.repo_id.split_once('/').context("repo id must be owner/name")?;
        let body = serde_json::json!({"name": name, "organization": owner, "private": self.opts.private, "type": "model"});
        let url = format!("{}/api/repos/create", self.opts.endpoint);
        match self.auth(self.agent.post(&url)).set("Content-Type", "application/json").send_string(&body.to_string()) {
            Ok(_) => Ok(true),
            Err(ureq::Error::Status(409, _)) => {
                if self.opts.private {
                    let what = format!("reading repo {}'s visibility", self.opts.repo_id);
                    let url = format!("{}/api/models/{}", self.opts.endpoint, self.opts.repo_id);
                    let info = Self::json(self.auth(self.agent.get(&url)).call().map_err(|e| call_error(&what, e))?, &what)?;
                    ensure!(
                        info.get("private").and_then(serde_json::Value::as_bool) == Some(true),
                        "repo {} exists and is public: --private would publish these weights in it; make it private on the Hub first, or push to a new repo",
                        self.opts.repo_id
                    );
                }
                Ok(false)
            }
            Err(e) => Err(call_error(&format!("creating repo {}", self.opts.repo_id), e)),
        }
    }

    fn preupload(&self, files: &[LocalFile]) -> Result<std::collections::BTreeMap<String, (String, bool)>> {
        let url = format!("{}/api/models/{}/preupload/{}", self.opts.endpoint, self.opts.repo_id, self.opts.revision);
        let mut modes = std::collections::BTreeMap::new();
        for chunk in files.chunks(256) {
            let payload: Vec<serde_json::Value> = chunk
                .iter()
                .map(|f| {
                    serde_json::json!({"path": f.rel, "size": f.size, "sample": base64::engine::general_purpose::STANDARD.encode(&f.sample)})
                })
                .collect();
            let answer = Self::json(self.post_json(&url, &serde_json::json!({"files": payload}), "preupload")?, "preupload")?;
            for f in answer.get("files").and_then(|f| f.as_array()).context("preupload: no \"files\" in the answer")? {
                let path = f.get("path").and_then(|p| p.as_str()).context("preupload: a file without path")?;
                let mode = f.get("uploadMode").and_then(|m| m.as_str()).unwrap_or("regular");
                let ignore = f.get("shouldIgnore").and_then(|m| m.as_bool()).unwrap_or(false);
                modes.insert(path.to_string(), (mode.to_string(), ignore));
            }
        }
        Ok(modes)
    }

    fn lfs_upload(&self, files: &[&LocalFile], progress: &mut dyn FnMut(&PushEvent)) -> Result<usize> {
        if files.is_empty() {
            return Ok(0);
        }
        let url = format!("{}/{}.git/info/lfs/objects/batch", self.opts.endpoint, self.opts.repo_id);
        let objects: Vec<serde_json::Value> = files.iter().map(|f| serde_json::json!({"oid": f.sha256, "size": f.size})).collect();
        let body = serde_json::json!({
            "operation": "upload", "transfers": ["basic", "multipart"], "objects": objects,
            "hash_algo": "sha256", "ref": {"name": self.opts.revision},
        });
        let resp = self
            .auth(self.agent.post(&url))
            .set("Accept", "application/vnd.git-lfs+json")
            .set("Content-Type", "application/vnd.git-lfs+json")
            .send_string(&body.to_string())
            .map_err(|e| call_error("LFS batch", e))?;
        let answer = Self::json(resp, "LFS batch")?;
        let objects = answer.get("objects").and_then(|o| o.as_array()).context("LFS batch: no \"objects\" in the answer")?;
        let mut skipped = 0;
        for obj in objects {
            let oid = obj.get("oid").and_then(|o| o.as_str()).unwrap_or_default();
            let file = files.iter().find(|f| f.sha256 == oid).with_context(|| format!("LFS batch: answer for unknown object {oid}"))?;
            if let Some(err) = obj.get("error") {
                bail!("LFS batch refused {} ({}): {}", file.rel, err.get("code").map(|c| c.to_string()).unwrap_or_default(), err.get("message").and_then(|m| m.as_str()).unwrap_or(""));
            }
            let Some(upload) = obj.get("actions").and_then(|a| a.get("upload")) else {
                skipped += 1;
                progress(&PushEvent::AlreadyOnHub { path: file.rel.clone() });
                continue;
            };
            let href = upload.get("href").and_then(|h| h.as_str()).with_context(|| format!("LFS batch: no upload href for {}", file.rel))?;
            let header = upload.get("header").and_then(|h| h.as_object()).cloned().unwrap_or_default();
            if let Some(chunk) = header.get("chunk_size") {
                let chunk: u64 = match chunk {
                    serde_json::Value::String(s) => s.parse().with_context(|| format!("LFS multipart: bad chunk_size '{s}'"))?,
                    v => v.as_u64().context("LFS multipart: bad chunk_size")?,
                };
                ensure!(chunk > 0, "LFS multipart: chunk_size 0");
                self.upload_multipart(file, href, &header, chunk, progress)?;
            } else {
                self.upload_basic(file, href, &header, progress)?;
            }
            if let Some(verify) = obj.get("actions").and_then(|a| a.get("verify")) {
                let vhref = verify.get("href").and_then(|h| h.as_str()).context("LFS verify action without href")?;
                let mut req = self.auth(self.agent.post(vhref)).set("Content-Type", "application/vnd.git-lfs+json");
                for (k, v) in verify.get("header").and_then(|h| h.as_object()).into_iter().flatten() {
                    req = req.set(k, v.as_str().unwrap_or_default());
                }
                req.send_string(&serde_json::json!({"oid": file.sha256, "size": file.size}).to_string())
                    .map_err(|e| call_error(&format!("verifying {}", file.rel), e))?;
            }
        }
        Ok(skipped)
    }

    fn upload_basic(
        &self,
        file: &LocalFile,
        href: &str,
        header: &serde_json::Map<String, serde_json::Value>,
        progress: &mut dyn FnMut(&PushEvent),
    ) -> Result<()> {
        let f = File::open(&file.path).with_context(|| format!("opening {}", file.path.display()))?;
        let mut req = self.agent.put(href).set("Content-Length", &file.size.to_string());
        for (k, v) in header {
            req = req.set(k, v.as_str().unwrap_or_default());
        }
        let reader = ProgressReader { inner: f, sent: 0, reported: 0, total: file.size, path: &file.rel, progress };
        req.send(reader).map_err(|e| call_error(&format!("uploading {}", file.rel), e))?;
        Ok(())
    }

    fn upload_multipart(
        &self,
        file: &LocalFile,
        href: &str,
        header: &serde_json::Map<String, serde_json::Value>,
        chunk: u64,
        progress: &mut dyn FnMut(&PushEvent),
    ) -> Result<()> {
        let mut parts: Vec<(u64, String)> = header
            .iter()
            .filter_map(|(k, v)| Some((k.parse::<u64>().ok()?, v.as_str()?.to_string())))
            .collect();
        parts.sort();
        let needed = file.size.div_ceil(chunk);
        ensure!(
            parts.len() as u64 == needed,
            "LFS multipart for {}: {} part URLs for {} bytes in chunks of {chunk} (expected {needed})",
            file.rel,
            parts.len(),
            file.size
        );
        let mut f = File::open(&file.path).with_context(|| format!("opening {}", file.path.display()))?;
        let mut done = Vec::new();
        let mut sent_before = 0u64;
        for (i, (number, url)) in parts.iter().enumerate() {
            let start = i as u64 * chunk;
            let len = chunk.min(file.size - start);
            f.seek(SeekFrom::Start(start))?;
            let mut buf = vec![0u8; len as usize];
            f.read_exact(&mut buf).with_context(|| format!("reading {}", file.path.display()))?;
            let resp = self
                .agent
                .put(url)
                .send_bytes(&buf)
                .map_err(|e| call_error(&format!("uploading part {number} of {}", file.rel), e))?;
            let etag = resp.header("ETag").or_else(|| resp.header("etag")).with_context(|| format!("part {number} of {}: no ETag in the answer", file.rel))?;
            done.push(serde_json::json!({"partNumber": number, "etag": etag}));
            sent_before += len;
            progress(&PushEvent::Uploading { path: file.rel.clone(), sent: sent_before, total: file.size });
        }
        self.auth(self.agent.post(href))
            .set("Content-Type", "application/vnd.git-lfs+json")
            .send_string(&serde_json::json!({"oid": file.sha256, "parts": done}).to_string())
            .map_err(|e| call_error(&format!("completing the multipart upload of {}", file.rel), e))?;
        Ok(())
    }

    /// The paths of the files at the pushed revision.
    fn remote_files(&self) -> Result<Vec<String>> {
        let what = format!("listing the files of {}", self.opts.repo_id);
        let url = format!("{}/api/models/{}/revision/{}", self.opts.endpoint, self.opts.repo_id, self.opts.revision);
        let info = Self::json(self.auth(self.agent.get(&url)).call().map_err(|e| call_error(&what, e))?, &what)?;
        let siblings = info.get("siblings").and_then(serde_json::Value::as_array).with_context(|| format!("{what}: no 'siblings' in the answer"))?;
        Ok(siblings.iter().filter_map(|s| s.get("rfilename").and_then(serde_json::Value::as_str).map(String::from)).collect())
    }

    fn commit(&self, files: &[LocalFile], lfs: &std::collections::BTreeSet<String>, deleted: &[String]) -> Result<serde_json::Value> {
        let mut body = String::new();
        let header = serde_json::json!({"key": "header", "value": {"summary": self.opts.commit_message, "description": ""}});
        body.push_str(&header.to_string());
        body.push('\n');
        for f in files {
            let line = if lfs.contains(&f.rel) {
                serde_json::json!({"key": "lfsFile", "value": {"path": f.rel, "algo": "sha256", "oid": f.sha256, "size": f.size}})
            } else {
                let bytes = std::fs::read(&f.path).with_context(|| format!("reading {}", f.path.display()))?;
                serde_json::json!({"key": "file", "value": {"content": base64::engine::general_purpose::STANDARD.encode(bytes), "path": f.rel, "encoding": "base64"}})
            };
            body.push_str(&line.to_string());
            body.push('\n');
        }
        for path in deleted {
            body.push_str(&serde_json::json!({"key": "deletedFile", "value": {"path": path}}).to_string());
            body.push('\n');
        }
        let url = format!("{}/api/models/{}/commit/{}", self.opts.endpoint, self.opts.repo_id, self.opts.revision);
        let resp = self
            .auth(self.agent.post(&url))
            .set("Content-Type", "application/x-ndjson")
            .send_string(&body)
            .map_err(|e| call_error("commit", e))?;
        Self::json(resp, "commit")
    }
}

struct ProgressReader<'a, R> {
    inner: R,
    sent: u64,
    reported: u64,
    total: u64,
    path: &'a str,
    progress: &'a mut dyn FnMut(&PushEvent),
}

impl<R: Read> Read for ProgressReader<'_, R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.sent += n as u64;
        if self.sent - self.reported >= (64 << 20) || (n == 0 && self.reported < self.sent) || self.sent == self.total && self.reported < self.total {
            self.reported = self.sent;
            (self.progress)(&PushEvent::Uploading { path: self.path.to_string(), sent: self.sent, total: self.total });
        }
        Ok(n)
    }
}

/// Uploads every file of `folder` (hidden files skipped) to the model repo `opts.repo_id` in one
/// commit, creating the repo when needed. An error when there is no token.
pub fn push_folder(folder: &Path, opts: &PushOptions, progress: &mut dyn FnMut(&PushEvent)) -> Result<PushReport> {
    ensure!(is_repo_id(&opts.repo_id) && !opts.repo_id.contains('@'), "--push expects OWNER/NAME, got '{}'", opts.repo_id);
    let token = opts.token.clone().with_context(|| {
        format!(
            "pushing to {} needs a Hugging Face token with write access: set HF_TOKEN (create one at {}/settings/tokens) or log in with `hf auth login`",
            opts.endpoint, opts.endpoint
        )
    })?;
    ensure!(folder.is_dir(), "{}: not a folder", folder.display());
    let hub = Hub { opts, token, agent: agent() };
    let created = hub.create_repo()?;
    let repo_url = format!("{}/{}", opts.endpoint, opts.repo_id);
    progress(&PushEvent::RepoReady { url: repo_url.clone(), created });

    let mut listed = Vec::new();
    collect_files(folder, folder, &mut listed)?;
    ensure!(!listed.is_empty(), "{}: nothing to upload", folder.display());
    let mut files = Vec::new();
    for (path, rel) in listed {
        let (size, sha256, sample) = hash_file(&path)?;
        progress(&PushEvent::Hashed { path: rel.clone(), bytes: size });
        files.push(LocalFile { path, rel, size, sha256, sample });
    }
    let modes = hub.preupload(&files)?;
    let files: Vec<LocalFile> = files.into_iter().filter(|f| !modes.get(&f.rel).is_some_and(|(_, ignore)| *ignore)).collect();
    let lfs: std::collections::BTreeSet<String> = files
        .iter()
        .filter(|f| f.size > 0 && modes.get(&f.rel).is_some_and(|(m, _)| m == "lfs"))
        .map(|f| f.rel.clone())
        .collect();
    let lfs_files: Vec<&LocalFile> = files.iter().filter(|f| lfs.contains(&f.rel)).collect();
    let lfs_skipped = hub.lfs_upload(&lfs_files, progress)?;
    // The repo's files become the folder's: what an existing repo holds beyond them goes in the
    // same commit (the Hub's own .gitattributes stays).
    let deleted: Vec<String> = if created {
        Vec::new()
    } else {
        let local: std::collections::BTreeSet<&str> = files.iter().map(|f| f.rel.as_str()).collect();
        hub.remote_files()?.into_iter().filter(|r| r != ".gitattributes" && !local.contains(r.as_str())).collect()
    };
    if !deleted.is_empty() {
        progress(&PushEvent::Deleting { paths: deleted.clone() });
    }
    progress(&PushEvent::Committing { files: files.len() });
    let answer = hub.commit(&files, &lfs, &deleted)?;
    let s = |k: &str| answer.get(k).and_then(|v| v.as_str()).map(String::from);
    Ok(PushReport {
        repo_url,
        commit_url: s("commitUrl"),
        commit_oid: s("commitOid"),
        lfs_files: lfs.len(),
        regular_files: files.len() - lfs.len(),
        lfs_skipped,
        deleted,
    })
}

/// Whether `s` reads as a Hub repo id (`owner/name`, optionally `@revision`).
pub fn is_repo_id(s: &str) -> bool {
    let id = s.split_once('@').map(|(a, _)| a).unwrap_or(s);
    let parts: Vec<&str> = id.split('/').collect();
    let ok = |p: &str| !p.is_empty() && !p.starts_with('.') && p.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c));
    parts.len() == 2 && parts.iter().all(|p| ok(p))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wanted_files_follow_indexes_and_skip_other_components() {
        let listing: Vec<String> = [
            "config.json", "diffusion_pytorch_model-00001-of-00002.safetensors", "diffusion_pytorch_model-00002-of-00002.safetensors",
            "diffusion_pytorch_model.safetensors.index.json", "Wan2.2_VAE.pth", "google/umt5-xxl/spiece.model", "README.md",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        let mut idx = |_: &str| Ok(vec!["diffusion_pytorch_model-00001-of-00002.safetensors".to_string(), "diffusion_pytorch_model-00002-of-00002.safetensors".to_string()]);
        let got = wanted_files(&listing, &mut idx).unwrap();
        assert_eq!(got.len(), 4, "{got:?}");
        assert!(!got.iter().any(|f| f.ends_with(".pth")));
        let listing: Vec<String> = ["model_index.json", "transformer/config.json", "transformer/diffusion_pytorch_model.safetensors", "vae/diffusion_pytorch_model.safetensors"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        let got = wanted_files(&listing, &mut |_| Ok(vec![])).unwrap();
        assert_eq!(got, vec!["transformer/config.json".to_string(), "transformer/diffusion_pytorch_model.safetensors".to_string()]);
    }

    #[test]
    fn no_token_is_a_clear_error() {
        let opts = PushOptions { token: None, ..PushOptions::new("me/model", false, &HubEnv { endpoint: "http://127.0.0.1:9".into(), ..Default::default() }) };
        let e = push_folder(Path::new("."), &opts, &mut |_| {}).unwrap_err().to_string();
        assert!(e.contains("HF_TOKEN"), "{e}");
    }
}
