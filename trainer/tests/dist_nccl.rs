//! The NCCL back end with two processes on two GPUs: the collectives, failures of a peer, and a
//! training run of 2 ranks against 1 rank. Ignored by default: it needs a machine with 2 GPUs and
//! libtorch's NCCL reachable as `libnccl.so`; `bash scripts/gpu/unit.sh nccl` runs them there
//! (BWM_REQUIRE set: with fewer than 2 GPUs they fail). By hand on such a machine
//! (docs/architecture.md, Toolchain facts):
//!
//! ```text
//! TL=$(python3 -c 'import torch,os;print(os.path.dirname(torch.__file__))')/lib
//! NL=$(python3 -c 'import nvidia;print(nvidia.__path__[0])')/nccl/lib
//! mkdir -p /tmp/nccl-link && ln -sf $NL/libnccl.so.2 /tmp/nccl-link/libnccl.so
//! export LD_LIBRARY_PATH=/tmp/nccl-link:$TL:$NL:$LD_LIBRARY_PATH NCCL_NVLS_ENABLE=0
//! ./dist_nccl-<hash> --ignored --test-threads=1 --nocapture
//! ```
//!
//! (the test binary built here by `cargo test --release -p bwm-trainer --test dist_nccl --no-run`,
//! which prints its path). Each test re-runs the binary once per rank with `BWM_DIST_TEST_ROLE`
//! (or `BWM_DIST_TEST_TRAIN`), RANK, LOCAL_RANK, WORLD_SIZE, MASTER_ADDR and MASTER_PORT set;
//! `nccl_child` and `train_child` are the ranks' entry points and do nothing without their
//! variable. The training comparison also runs on the CPU over TCP (not ignored): the same
//! processes, files and tolerances, so that everything but NCCL itself is checked everywhere.

mod common;

use bwm_testdir::{need, Dep};
use bwm_trainer::dist::{ensure_torch_cuda_loaded, Collective, NcclCollective};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};
use tch::{Device, Kind, Tensor};

const ROLE: &str = "BWM_DIST_TEST_ROLE";
const KINDS: [Kind; 4] = [Kind::Float, Kind::BFloat16, Kind::Half, Kind::Double];
const N: usize = 1000;

fn input(kind: Kind, rank: usize, n: usize) -> Tensor {
    let v: Vec<f64> = (0..n).map(|i| ((i * 37 + rank * 101) % 1000) as f64 / 7.0 - 50.0 + rank as f64 * 1e-3).collect();
    Tensor::from_slice(&v).to_kind(kind)
}

/// Sum (or mean) over ranks in rank order, f64 for f64 and f32 rounded once otherwise: for two
/// ranks this is what NCCL computes too (one addition per element, halving is exact).
fn expected_reduce(kind: Kind, world: usize, n: usize, mean: bool) -> Tensor {
    if kind == Kind::Double {
        let xs: Vec<Vec<f64>> = (0..world).map(|r| Vec::try_from(&input(kind, r, n)).unwrap()).collect();
        let s: Vec<f64> = (0..n).map(|i| xs[1..].iter().fold(xs[0][i], |a, x| a + x[i])).map(|s| if mean { s / world as f64 } else { s }).collect();
        return Tensor::from_slice(&s);
    }
    let xs: Vec<Vec<f32>> = (0..world).map(|r| Vec::try_from(&input(kind, r, n)).unwrap()).collect();
    let s: Vec<f32> = (0..n).map(|i| xs[1..].iter().fold(xs[0][i], |a, x| a + x[i])).map(|s| if mean { s / world as f32 } else { s }).collect();
    Tensor::from_slice(&s).to_kind(kind)
}

fn bits(t: &Tensor) -> Vec<u64> {
    let flat = t.to_device(Device::Cpu).reshape([-1]);
    if t.kind() == Kind::Double {
        Vec::<f64>::try_from(&flat).unwrap().iter().map(|x| x.to_bits()).collect()
    } else {
        Vec::<f32>::try_from(&flat).unwrap().iter().map(|x| x.to_bits() as u64).collect()
    }
}

fn assert_bits(got: &Tensor, want: &Tensor, what: &str) {
    assert_eq!((got.kind(), got.size()), (want.kind(), want.size()), "{what}");
    assert!(bits(got) == bits(want), "{what}: values differ");
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn spawn(role: &str, rank: usize, port: u16, timeout_s: u32) -> Child {
    Command::new(std::env::current_exe().unwrap())
        .args(["--exact", "nccl_child", "--nocapture", "--test-threads=1"])
        .env(ROLE, role)
        .env("RANK", rank.to_string())
        .env("LOCAL_RANK", rank.to_string())
        .env("WORLD_SIZE", "2")
        .env("MASTER_ADDR", "127.0.0.1")
        .env("MASTER_PORT", port.to_string())
        .env("BWM_DIST_TIMEOUT", timeout_s.to_string())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

fn finish(child: Child, what: &str) -> Output {
    let out = child.wait_with_output().unwrap();
    println!("--- {what} ({}) ---\n{}{}", out.status, String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    out
}

/// Whether libtorch's CUDA is loaded and sees 2 GPUs. Without them the test fails when
/// BWM_REQUIRE names nccl (scripts/gpu/unit.sh sets it) and is logged as skipped otherwise.
fn two_gpus() -> bool {
    let missing = match ensure_torch_cuda_loaded() {
        Err(e) => Some(format!("{e:#}")),
        Ok(()) => {
            let n = tch::Cuda::device_count();
            (n < 2).then(|| format!("2 GPUs needed, {n} visible"))
        }
    };
    need(Dep::Nccl, missing)
}

/// Every operation on f32, bf16, f16 and f64, checked exactly, then all-reduce bandwidth.
#[test]
#[ignore = "needs 2 GPUs and NCCL (scripts/gpu/unit.sh nccl)"]
fn nccl_two_processes_give_exact_values() {
    if !two_gpus() {
        return;
    }
    let port = free_port();
    let children: Vec<Child> = (0..2).map(|r| spawn("ops", r, port, 120)).collect();
    for (r, c) in children.into_iter().enumerate() {
        assert!(finish(c, &format!("rank {r}")).status.success(), "rank {r} failed");
    }
}

/// Rank 1's process dies while rank 0 is inside an all-reduce: rank 0 fails fast, not at the timeout.
#[test]
#[ignore = "needs 2 GPUs and NCCL (scripts/gpu/unit.sh nccl)"]
fn nccl_peer_killed_mid_collective_is_an_error() {
    if !two_gpus() {
        return;
    }
    let port = free_port();
    let survivor = spawn("survivor", 0, port, 60);
    let victim = spawn("dies", 1, port, 60);
    let v = finish(victim, "rank 1");
    assert_eq!(v.status.code(), None, "rank 1 should have died of a signal");
    assert!(finish(survivor, "rank 0").status.success(), "rank 0 did not report the failure correctly");
}

/// Rank 1 stops calling collectives: rank 0 times out, names rank 1, and rank 1 then fails too.
#[test]
#[ignore = "needs 2 GPUs and NCCL (scripts/gpu/unit.sh nccl)"]
fn nccl_peer_that_stops_responding_is_named() {
    if !two_gpus() {
        return;
    }
    let port = free_port();
    let children = [spawn("waits", 0, port, 5), spawn("sleeps", 1, port, 5)];
    for (r, c) in children.into_iter().enumerate() {
        assert!(finish(c, &format!("rank {r}")).status.success(), "rank {r} failed");
    }
}

/// 2 ranks of one micro-step each train as 1 rank of two micro-steps (the same global batch of
/// 2, the same samples), with the blocks' gradients reduced during the backward walk (the
/// default) or after it, on two GPUs over NCCL in bf16 with the optimizer state sharded (ZeRO-1).
#[test]
#[ignore = "needs 2 GPUs and NCCL (scripts/gpu/unit.sh nccl)"]
fn nccl_two_ranks_train_as_one_rank_with_the_same_global_batch() {
    if !two_gpus() {
        return;
    }
    ranks_train_as_one("nccl", "cuda");
}

/// The same comparison on the CPU over TCP: everything of the NCCL test above but NCCL itself.
#[test]
fn tcp_two_ranks_train_as_one_rank_with_the_same_global_batch() {
    ranks_train_as_one("tcp", "cpu");
}

/// What one rank of a training run writes for the comparison (`train_child`), read back.
struct RankResult {
    /// This rank's slice of the flat fp32 master weights: its first element's index, before the
    /// first step and after the last.
    start: i64,
    master_init: Tensor,
    master: Tensor,
    /// Per step: the loss over the global batch and the gradient norm after the reduction.
    losses: Vec<f64>,
    grad_norms: Vec<f64>,
}

/// A run's fp32 master weights, before and after, assembled from its ranks' slices; its losses
/// and gradient norms (the same on every rank: rank 0's).
struct RunResult {
    master_init: Tensor,
    master: Tensor,
    losses: Vec<f64>,
    grad_norms: Vec<f64>,
}

/// Relative difference allowed between the runs (their updates, losses and gradient norms):
/// 2^-6, a few units of bf16 rounding (2^-8). Each rank computes its sample's bf16 gradients as
/// the one rank does, and both sum them in fp32; the runs differ where values are rounded in
/// another order: the gradient norm that sets the clipping is summed over the shards of the
/// optimizer state (on the CPU this alone leaves the updates 8e-7 apart), a GPU's kernels that
/// add with atomics can round a bf16 gradient to its neighbour, and a master that differs in its
/// last bits can round to the neighbouring bf16 weight, which the next step's forward reads. A
/// rank's gradient lost, counted twice or taken from the wrong sample moves the update or the
/// gradient norm by tens of percent.
const BF16_TOL: f64 = 1.0 / 64.0;

/// Trains the tiny config (bf16, 3 steps, global batch 2) as 1 rank with 2 micro-steps, as 2
/// ranks with the reduction overlapped with the backward walk, and as 2 ranks reducing after it,
/// each rank a process of this test binary on `device`; compares the three within [`BF16_TOL`],
/// and a run of half the batch (1 rank, 1 micro-step: what a rank alone would train) beyond it.
fn ranks_train_as_one(tag: &str, device: &str) {
    let dir = common::tmp_dir(&format!("ranks-as-one-{tag}"));
    let cache = common::write_cache(&dir.join("cache"), 4, 21);
    let base = format!("[run]\ndevice = \"{device}\"\n[model]\ndtype = \"bf16\"\n[train]\nsteps = 3\nmicro_batch = 1\n");
    let one = train_ranks(&dir, &cache, "one", 1, &format!("{base}grad_accum = 2\n"));
    let two = train_ranks(&dir, &cache, "two", 2, &format!("{base}grad_accum = 1\noverlap_grad_reduce = true\n"));
    let after = train_ranks(&dir, &cache, "after-walk", 2, &format!("{base}grad_accum = 1\noverlap_grad_reduce = false\n"));
    let half = train_ranks(&dir, &cache, "half", 1, &format!("{base}grad_accum = 1\n"));
    assert_eq!(one.master_init, two.master_init, "{tag}: the runs start from different weights");
    for (a, b, what) in [(&two, &one, "2 ranks against 1 rank of 2 micro-steps"), (&after, &two, "the reduction after the backward walk against during it")] {
        let d = apart(a, b, &format!("{tag}: {what}"));
        assert!(d <= BF16_TOL, "{tag}: {what}: {d:.3e} apart (relative)");
    }
    let d = apart(&half, &one, &format!("{tag}: half the batch against the whole"));
    assert!(d > 4.0 * BF16_TOL, "{tag}: a run of half the batch is only {d:.3e} from the whole: the comparison cannot tell them apart");
}

/// The largest relative difference between runs `a` and `b`: of their weight updates (relative to
/// `b`'s size), and of each step's loss and gradient norm.
fn apart(a: &RunResult, b: &RunResult, what: &str) -> f64 {
    let norm = |t: &Tensor| t.to_kind(Kind::Double).norm().double_value(&[]);
    let update = norm(&(&b.master - &b.master_init));
    assert!(update > 0.0, "{what}: the weights did not move");
    let weights = norm(&(&a.master - &b.master)) / update;
    assert_eq!((a.losses.len(), a.grad_norms.len(), b.losses.len()), (3, 3, 3), "{what}: steps logged");
    let pairs = a.losses.iter().zip(&b.losses).chain(a.grad_norms.iter().zip(&b.grad_norms));
    let steps = pairs.map(|(x, y)| (x - y).abs() / y.abs()).fold(0.0, f64::max);
    println!("{what}: weight updates {weights:.3e} apart (relative), losses and gradient norms {steps:.3e}; losses {:?} / {:?}; gradient norms {:?} / {:?}", a.losses, b.losses, a.grad_norms, b.grad_norms);
    weights.max(steps)
}

/// A run of `world` ranks (processes of this binary, `train_child`) of the tiny config on `cache`
/// with `extra`, in `dir/name`; its ranks' results assembled.
fn train_ranks(dir: &Path, cache: &Path, name: &str, world: usize, extra: &str) -> RunResult {
    let out = dir.join(name);
    let port = free_port();
    let children: Vec<Child> = (0..world)
        .map(|rank| {
            let mut c = Command::new(std::env::current_exe().unwrap());
            c.args(["--exact", "train_child", "--nocapture", "--test-threads=1"])
                .env(TRAIN, &out)
                .env("BWM_DIST_TEST_CACHE", cache)
                .env("BWM_DIST_TEST_EXTRA", extra)
                .env("BWM_DIST_TIMEOUT", "120")
                .stdout(Stdio::piped())
                .stderr(Stdio::piped());
            for var in ["RANK", "LOCAL_RANK", "WORLD_SIZE", "LOCAL_WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT"] {
                c.env_remove(var);
            }
            if world > 1 {
                c.env("RANK", rank.to_string())
                    .env("LOCAL_RANK", rank.to_string())
                    .env("WORLD_SIZE", world.to_string())
                    .env("MASTER_ADDR", "127.0.0.1")
                    .env("MASTER_PORT", port.to_string());
            }
            c.spawn().unwrap()
        })
        .collect();
    for (rank, c) in children.into_iter().enumerate() {
        assert!(finish(c, &format!("{name}, rank {rank}")).status.success(), "{name}: rank {rank} failed");
    }
    let mut ranks: Vec<RankResult> = (0..world).map(|rank| read_rank(&out.join(format!("rank-{rank}.safetensors")))).collect();
    ranks.sort_by_key(|r| r.start);
    let mut next = 0;
    for r in &ranks {
        assert_eq!(r.start, next, "{name}: the ranks' slices of the master weights do not tile it");
        next += r.master.size()[0];
    }
    let cat = |f: fn(&RankResult) -> &Tensor| Tensor::cat(&ranks.iter().map(f).collect::<Vec<_>>(), 0);
    let (master_init, master) = (cat(|r| &r.master_init), cat(|r| &r.master));
    let first = ranks.iter().find(|r| r.start == 0).unwrap();
    for r in &ranks {
        assert_eq!((&r.losses, &r.grad_norms), (&first.losses, &first.grad_norms), "{name}: the ranks disagree on the losses or gradient norms");
    }
    RunResult { master_init, master, losses: first.losses.clone(), grad_norms: first.grad_norms.clone() }
}

fn read_rank(path: &Path) -> RankResult {
    let t: std::collections::HashMap<String, Tensor> = Tensor::read_safetensors(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).into_iter().collect();
    let f64s = |k: &str| Vec::<f64>::try_from(&t[k]).unwrap();
    RankResult {
        start: t["start"].int64_value(&[0]),
        master_init: t["master_init"].shallow_clone(),
        master: t["master"].shallow_clone(),
        losses: f64s("losses"),
        grad_norms: f64s("grad_norms"),
    }
}

/// The training run's folder; set, the process is one rank of `train_ranks`.
const TRAIN: &str = "BWM_DIST_TEST_TRAIN";

/// Entry point of `train_ranks`' processes (a no-op unless `BWM_DIST_TEST_TRAIN` is set): trains
/// the run as this rank and writes `rank-R.safetensors` beside it.
#[test]
fn train_child() {
    let Some(out) = std::env::var_os(TRAIN).map(PathBuf::from) else { return };
    let cache = PathBuf::from(std::env::var_os("BWM_DIST_TEST_CACHE").unwrap());
    let cfg = common::config(&cache, &out, &std::env::var("BWM_DIST_TEST_EXTRA").unwrap());
    if cfg.run.device != "cpu" {
        // Before libtorch is first asked about CUDA (the test binary may lack libtorch_cuda).
        ensure_torch_cuda_loaded().unwrap();
    }
    let mut t = common::trainer(cfg, bwm_trainer::Resume::No).unwrap();
    let start = t.opt.slice().start as i64;
    let master_init = t.opt.master.to_device(Device::Cpu).copy();
    t.run().unwrap();
    let steps: Vec<&bwm_trainer::metrics::StepMetrics> = t.history.iter().collect();
    let losses: Vec<f64> = steps.iter().map(|m| m.loss).collect();
    let grad_norms: Vec<f64> = steps.iter().map(|m| m.grad_norm.unwrap_or(f64::NAN)).collect();
    let tensors = [
        ("start", Tensor::from_slice(&[start])),
        ("master_init", master_init),
        ("master", t.opt.master.to_device(Device::Cpu)),
        ("losses", Tensor::from_slice(&losses)),
        ("grad_norms", Tensor::from_slice(&grad_norms)),
    ];
    Tensor::write_safetensors(&tensors, out.join(format!("rank-{}.safetensors", t.comm.rank()))).unwrap();
}

/// Entry point of the rank processes (a no-op unless `BWM_DIST_TEST_ROLE` is set).
#[test]
fn nccl_child() {
    let Ok(role) = std::env::var(ROLE) else { return };
    let t0 = Instant::now();
    let mut c = NcclCollective::from_env().unwrap();
    let (rank, world, dev) = (c.rank(), c.world_size(), c.device());
    println!("rank {rank}: communicator ready in {:.2?}", t0.elapsed());
    let mut warm = Tensor::ones([4], (Kind::Float, dev));
    c.all_reduce_sum(&mut warm).unwrap();
    assert_bits(&warm, &Tensor::full([4], 2.0, (Kind::Float, Device::Cpu)), "warm-up");
    match role.as_str() {
        "ops" => {
            for kind in KINDS {
                let mut t = input(kind, rank, N).to_device(dev);
                c.all_reduce_sum(&mut t).unwrap();
                assert_bits(&t, &expected_reduce(kind, world, N, false), &format!("all_reduce_sum {kind:?}"));
                let mut t = input(kind, rank, N).to_device(dev);
                c.all_reduce_mean(&mut t).unwrap();
                assert_bits(&t, &expected_reduce(kind, world, N, true), &format!("all_reduce_mean {kind:?}"));
                // A non-contiguous tensor goes through a contiguous copy and back.
                let base = input(kind, rank, 2 * N).reshape([2, N as i64]).to_device(dev);
                let mut view = base.tr();
                c.all_reduce_sum(&mut view).unwrap();
                assert_bits(&base.reshape([-1]), &expected_reduce(kind, world, 2 * N, false), &format!("all_reduce_sum {kind:?} view"));
                let full = input(kind, rank, world * N).to_device(dev);
                let mut shard = Tensor::zeros([N as i64], (kind, dev));
                c.reduce_scatter_sum(&full, &mut shard).unwrap();
                let want = expected_reduce(kind, world, world * N, false).narrow(0, (rank * N) as i64, N as i64);
                assert_bits(&shard, &want, &format!("reduce_scatter_sum {kind:?}"));
                let mut gathered = Tensor::zeros([(world * N) as i64], (kind, dev));
                c.all_gather(&input(kind, rank, N).to_device(dev), &mut gathered).unwrap();
                let want = Tensor::cat(&(0..world).map(|r| input(kind, r, N)).collect::<Vec<_>>(), 0);
                assert_bits(&gathered, &want, &format!("all_gather {kind:?}"));
                for root in 0..world {
                    let mut t = input(kind, rank, N).to_device(dev);
                    c.broadcast(&mut t, root).unwrap();
                    assert_bits(&t, &input(kind, root, N), &format!("broadcast {kind:?} from {root}"));
                }
                c.barrier().unwrap();
            }
            // Started reductions run on the side stream while later kernels run on the default
            // one; a later collective and `finish_started` order everything after them.
            for kind in KINDS {
                let buffer = input(kind, rank, 3 * N).to_device(dev);
                let part = |i: i64| buffer.narrow(0, i * N as i64, N as i64);
                c.start_reduce_sum(&part(0), Some(0)).unwrap();
                c.start_reduce_sum(&part(1), Some(world - 1)).unwrap();
                let busy = Tensor::ones([2048, 2048], (Kind::Float, dev)).matmul(&Tensor::ones([2048, 2048], (Kind::Float, dev)));
                c.start_reduce_sum(&part(2), None).unwrap();
                let mut t = input(kind, rank, N).to_device(dev);
                c.all_reduce_sum(&mut t).unwrap();
                assert_bits(&t, &expected_reduce(kind, world, N, false), &format!("all_reduce_sum {kind:?} after started reductions"));
                c.finish_started().unwrap();
                let whole = expected_reduce(kind, world, 3 * N, false);
                let mine = input(kind, rank, 3 * N);
                for (i, root) in [Some(0), Some(world - 1), None].into_iter().enumerate() {
                    let want = if root.is_none_or(|r| r == rank) { &whole } else { &mine };
                    let want = want.narrow(0, (i * N) as i64, N as i64);
                    assert_bits(&part(i as i64), &want, &format!("start_reduce_sum {kind:?} to {root:?}"));
                }
                assert_eq!(busy.double_value(&[0, 0]), 2048.0);
            }
            assert!(c.take_collective_seconds() > 0.0, "collective time is measured");
            let mut ints = Tensor::from_slice(&[rank as i64 + 1, 7]).to_device(dev);
            c.all_reduce_sum(&mut ints).unwrap();
            assert_eq!(Vec::<i64>::try_from(&ints.to_device(Device::Cpu)).unwrap(), vec![3, 14]);
            let err = c.all_reduce_sum(&mut Tensor::ones([2], (Kind::Float, Device::Cpu))).unwrap_err();
            assert!(format!("{err:#}").contains("tensor on Cpu"), "{err:#}");
            // All-reduce bandwidth, 256 MiB of bf16 (busbw as nccl-tests define it).
            let mut big = Tensor::ones([128 << 20], (Kind::BFloat16, dev));
            c.all_reduce_sum(&mut big).unwrap();
            let iters = 20;
            let t = Instant::now();
            for _ in 0..iters {
                c.all_reduce_sum(&mut big).unwrap();
            }
            let per = t.elapsed().as_secs_f64() / iters as f64;
            let algbw = (256u64 << 20) as f64 / per / 1e9;
            println!(
                "rank {rank}: all_reduce 256 MiB bf16: {:.2} ms, algbw {algbw:.1} GB/s, busbw {:.1} GB/s",
                per * 1e3,
                algbw * 2.0 * (world - 1) as f64 / world as f64
            );
            c.barrier().unwrap();
        }
        "dies" => {
            std::thread::sleep(Duration::from_secs(2));
            println!("rank 1: exiting abnormally while rank 0 waits in an all-reduce");
            std::process::abort();
        }
        "survivor" => {
            let start = Instant::now();
            let mut t = Tensor::ones([1 << 20], (Kind::Float, dev));
            let err = format!("{:#}", c.all_reduce_sum(&mut t).unwrap_err());
            let took = start.elapsed();
            println!("rank 0: failed after {took:.2?}: {err}");
            assert!(err.contains("all_reduce_sum (op #2") && err.contains("rank 1"), "{err}");
            let later = format!("{:#}", c.barrier().unwrap_err());
            assert!(later.contains("aborted"), "{later}");
        }
        "waits" => {
            let start = Instant::now();
            let mut t = Tensor::ones([1 << 20], (Kind::Float, dev));
            let err = format!("{:#}", c.all_reduce_sum(&mut t).unwrap_err());
            let took = start.elapsed();
            println!("rank 0: failed after {took:.2?}: {err}");
            assert!(err.contains("all_reduce_sum (op #2") && err.contains("rank 1 (last at op #1) did not start it"), "{err}");
            // Stay until rank 1 has seen the failure.
            std::thread::sleep(Duration::from_secs(4));
        }
        "sleeps" => {
            std::thread::sleep(Duration::from_secs(7));
            let start = Instant::now();
            let err = format!("{:#}", c.barrier().unwrap_err());
            println!("rank 1: failed after {:.2?}: {err}", start.elapsed());
            assert!(err.contains("rank 0 reports") && err.contains("did not start it"), "{err}");
        }
        other => panic!("unknown role {other}"),
    }
    println!("rank {rank}: {role} done");
}
