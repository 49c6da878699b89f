//! Helpers of the end-to-end tests: the `bwm` binary, the project's Python, the bundled dataset, a
//! small random VAE file, a synthetic latent cache written through the real cache writer, tiny CPU
//! run configs, checkpoint comparison, and processes that die with the test.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use bwm_data::latent_cache::{CacheIndex, CacheWriter, ClipEntry};
use tch::{Device, Kind, Tensor};

pub fn bwm() -> PathBuf {
    // target/<profile>/deps/<test>-* -> target/<profile>/bwm
    let exe = std::env::current_exe().unwrap();
    let path = exe.parent().unwrap().parent().unwrap().join("bwm");
    assert!(
        path.exists(),
        "{} not built (run through `cargo test --workspace`)",
        path.display()
    );
    path
}

/// The virtualenv's python (VIRTUAL_ENV, BWM_VENV, else the repository's .venv:
/// `bwm_testdir::python`). The virtualenv is no optional dependency of these tests: it holds the
/// libtorch the `bwm` binary runs on, so a missing one fails the test here with what to do. A test
/// that needs packages beyond the set-up's core ones asks `bwm_testdir::python_with`.
pub fn python() -> String {
    match bwm_testdir::python() {
        Some(p) => p.display().to_string(),
        None => panic!("no virtualenv python (VIRTUAL_ENV, BWM_VENV or .venv): run `make setup` and `source scripts/env.sh`"),
    }
}

/// The bundled RoboTwin episodes in the BWM layout: the repository's `data/bwm-demo`, or
/// `$BWM_SHARED/data/bwm-demo` when BWM_SHARED is set (`bwm_testdir::demo_data`).
/// `bwm SUBCOMMAND` of the tiny model with random weights on CPU (4 history and 4 future frames,
/// 2 sampler steps, 64x32), then `args`; its output printed, which the test harness shows when the
/// test fails.
pub fn tiny_world_model(subcommand: &str, args: &[&str]) -> std::process::Output {
    let out = std::process::Command::new(bwm())
        .arg(subcommand)
        .args(["--random-weights", "tiny", "--history", "4", "--future", "4", "--sample-steps", "2", "--resolution", "64x32"])
        .args(["--device", "cpu"])
        .args(args)
        .output()
        .unwrap();
    println!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    out
}

pub fn demo_data() -> PathBuf {
    bwm_testdir::demo_data()
}

/// A small random VAE (width 16) written as `bwm train-vae` writes its output (recorded as trained
/// on 5-frame clips, the command's default), so that
/// `WanVae::load_any` reads it back with its config and latent statistics.
pub fn write_random_vae(path: &Path, seed: i64) {
    use bwm_model::vae::{VaeConfig, WanVae};
    use bwm_trainer::vae_train::{save_trained_vae, TrainedVae, VaeTrainReport};
    let (vae, store) = WanVae::random(&VaeConfig::with_width(16, 16), Kind::Float, Device::Cpu, seed).unwrap();
    let params = store.named_parameters();
    let report = VaeTrainReport { train_psnr: 0.0, holdout_psnr: 0.0, seconds: 0.0, steps: 0, clip_frames: 5, seed: 0, candidates: vec![(0, 0.0)], candidates_step: 0 };
    save_trained_vae(&TrainedVae { vae, params, report }, path).unwrap();
}

#[allow(unused_imports)]
pub use bwm_testdir::{shared_dir, tmp_dir as temp_dir, TestDir};

pub fn write_cache(dir: &Path) {
    // Drawn under with_seed's lock, so every caller writes the same clips.
    let clips: Vec<(Tensor, Tensor)> = bwm_model::vb::with_seed(0, || {
        (0..3).map(|_| (Tensor::randn([48, 4, 4, 4], (Kind::Float, Device::Cpu)), Tensor::rand([13, 14], (Kind::Float, Device::Cpu)) * 2.0 - 1.0)).collect()
    });
    let index = CacheIndex::new(vec![48, 4, 4, 4], 14, 8, 4, [64, 64], 30.0, "synthetic");
    let mut w = CacheWriter::create(dir, index).unwrap();
    for (episode, (latents, actions)) in (0..).zip(clips) {
        w.add(
            ClipEntry {
                file: String::new(),
                episode,
                frames: (0..13).collect(),
                task: "t".into(),
            },
            &latents,
            &actions,
            None,
        )
        .unwrap();
    }
    w.finish().unwrap();
}

/// A tiny CPU run reading `dir/cache`, checkpointing every step, writing to `out`.
pub fn write_config(dir: &Path, name: &str, out: &Path, steps: u64, grad_accum: usize) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(
        &path,
        format!(
            r#"[run]
name = "launch"
out_dir = "{out}"
device = "cpu"
[model]
preset = "tiny"
dtype = "f32"
[data]
latent_cache = "{cache}"
[optim]
lr = 1e-3
[train]
steps = {steps}
grad_accum = {grad_accum}
[checkpoint]
every = 1
keep_last = 20
[log]
progress = false
"#,
            out = out.display(),
            cache = dir.join("cache").display()
        ),
    )
    .unwrap();
    path
}

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Two consecutive free ports (rank 0's and the launchers' agent store's).
pub fn free_port_pair() -> u16 {
    loop {
        let p = free_port();
        if p < u16::MAX && std::net::TcpListener::bind(("127.0.0.1", p + 1)).is_ok() {
            return p;
        }
    }
}

/// The step of the run's `latest` checkpoint.
pub fn latest_step(run: &Path) -> u64 {
    let latest = std::fs::read_to_string(run.join("checkpoints/latest")).unwrap();
    latest
        .trim()
        .strip_prefix("step-")
        .unwrap()
        .parse()
        .unwrap()
}

pub fn final_weights(run: &Path) -> Vec<(String, Tensor)> {
    let latest = std::fs::read_to_string(run.join("checkpoints/latest")).unwrap();
    let mut t = Tensor::read_safetensors(
        run.join("checkpoints")
            .join(latest.trim())
            .join("model.safetensors"),
    )
    .unwrap();
    t.sort_by(|a, b| a.0.cmp(&b.0));
    t
}

pub fn assert_close(a: &[(String, Tensor)], b: &[(String, Tensor)], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}");
    for ((n, x), (m, y)) in a.iter().zip(b) {
        assert_eq!(n, m);
        let d = (x - y).abs().max().double_value(&[]);
        assert!(d <= 1e-5, "{what}: {n} differs by {d}");
    }
}

/// A `bwm` process whose stdout and stderr lines are collected (and echoed, for failing tests) as
/// they come; dropped, it is killed together with its children (a launcher's ranks).
pub struct Proc {
    pub child: std::process::Child,
    pub name: String,
    lines: std::sync::mpsc::Receiver<String>,
    pub output: Vec<String>,
}

impl Proc {
    pub fn spawn(name: &str, cmd: &mut std::process::Command) -> Proc {
        use std::io::{BufRead, BufReader};
        let mut child = cmd
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        let out = child.stdout.take().unwrap();
        let err = child.stderr.take().unwrap();
        let tx2 = tx.clone();
        std::thread::spawn(move || {
            BufReader::new(out)
                .lines()
                .map_while(Result::ok)
                .for_each(|l| drop(tx.send(l)))
        });
        std::thread::spawn(move || {
            BufReader::new(err)
                .lines()
                .map_while(Result::ok)
                .for_each(|l| drop(tx2.send(l)))
        });
        Proc {
            child,
            name: name.to_string(),
            lines: rx,
            output: Vec::new(),
        }
    }

    fn take(&mut self, line: String) -> String {
        eprintln!("[{}] {line}", self.name);
        self.output.push(line.clone());
        line
    }

    /// Reads lines until one satisfies `pred` (returned), or panics after `timeout`.
    pub fn wait_for(
        &mut self,
        what: &str,
        timeout: std::time::Duration,
        pred: impl Fn(&str) -> bool,
    ) -> String {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(l) => {
                    let l = self.take(l);
                    if pred(&l) {
                        return l;
                    }
                }
                Err(_) => panic!("{}: no line {what} within {timeout:?}", self.name),
            }
        }
    }

    /// Waits for the exit (killing it after `timeout`) and for the rest of its output.
    pub fn finish(&mut self, timeout: std::time::Duration) -> std::process::ExitStatus {
        let deadline = std::time::Instant::now() + timeout;
        let status = loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                break s;
            }
            while let Ok(l) = self.lines.try_recv() {
                self.take(l);
            }
            if std::time::Instant::now() > deadline {
                self.kill_tree();
                panic!("{} did not exit within {timeout:?}", self.name);
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        };
        // The pipes close when the ranks that inherited them have exited too.
        while let Ok(l) = self.lines.recv_timeout(std::time::Duration::from_secs(5)) {
            self.take(l);
        }
        status
    }

    pub fn text(&self) -> String {
        self.output.join("\n")
    }

    pub fn children(&self) -> Vec<u32> {
        let pid = self.child.id();
        std::fs::read_to_string(format!("/proc/{pid}/task/{pid}/children"))
            .unwrap_or_default()
            .split_whitespace()
            .filter_map(|p| p.parse().ok())
            .collect()
    }

    pub fn signal(&self, sig: &str) {
        signal(self.child.id(), sig);
    }

    fn kill_tree(&mut self) {
        for c in self.children() {
            signal(c, "KILL");
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            self.kill_tree();
        }
    }
}

pub fn signal(pid: u32, sig: &str) {
    let ok = std::process::Command::new("sh")
        .arg("-c")
        .arg(format!("kill -{sig} {pid}"))
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill -{sig} {pid}");
}
