//! The NCCL back end with two processes on two GPUs. Ignored by default: it needs a machine with 2
//! GPUs and libtorch's NCCL reachable as `libnccl.so`. On such a machine (ARCHITECTURE.md,
//! Toolchain facts):
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
//! which prints its path). Each test re-runs the binary once per rank with `BWM_DIST_TEST_ROLE`,
//! RANK, LOCAL_RANK, WORLD_SIZE, MASTER_ADDR and MASTER_PORT set; `nccl_child` is the ranks' entry
//! point and does nothing without that variable.

use bwm_trainer::dist::{ensure_torch_cuda_loaded, Collective, NcclCollective};
use std::net::TcpListener;
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

fn two_gpus() {
    ensure_torch_cuda_loaded().unwrap();
    let n = tch::Cuda::device_count();
    assert!(n >= 2, "these tests need 2 GPUs, {n} visible");
}

/// Every operation on f32, bf16, f16 and f64, checked exactly, then all-reduce bandwidth.
#[test]
#[ignore]
fn nccl_two_processes_give_exact_values() {
    two_gpus();
    let port = free_port();
    let children: Vec<Child> = (0..2).map(|r| spawn("ops", r, port, 120)).collect();
    for (r, c) in children.into_iter().enumerate() {
        assert!(finish(c, &format!("rank {r}")).status.success(), "rank {r} failed");
    }
}

/// Rank 1's process dies while rank 0 is inside an all-reduce: rank 0 fails fast, not at the timeout.
#[test]
#[ignore]
fn nccl_peer_killed_mid_collective_is_an_error() {
    two_gpus();
    let port = free_port();
    let survivor = spawn("survivor", 0, port, 60);
    let victim = spawn("dies", 1, port, 60);
    let v = finish(victim, "rank 1");
    assert_eq!(v.status.code(), None, "rank 1 should have died of a signal");
    assert!(finish(survivor, "rank 0").status.success(), "rank 0 did not report the failure correctly");
}

/// Rank 1 stops calling collectives: rank 0 times out, names rank 1, and rank 1 then fails too.
#[test]
#[ignore]
fn nccl_peer_that_stops_responding_is_named() {
    two_gpus();
    let port = free_port();
    let children = [spawn("waits", 0, port, 5), spawn("sleeps", 1, port, 5)];
    for (r, c) in children.into_iter().enumerate() {
        assert!(finish(c, &format!("rank {r}")).status.success(), "rank {r} failed");
    }
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
