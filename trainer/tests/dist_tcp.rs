//! The TCP (CPU) collective back end: every operation against exact expected values on 2 and 3
//! ranks (threads, and real processes), bit-identical results on every rank, and failures: calls
//! that do not match, a rank that never joins a collective, a rank that exits, a process killed in
//! the middle of a collective.
//!
//! The process tests re-run this test binary with `BWM_DIST_TEST_ROLE` set; the `child_process`
//! test is the child's entry point and does nothing without that variable.

use bwm_trainer::dist::{Collective, TcpCollective};
use std::net::TcpListener;
use std::process::{Child, Command, Stdio};
use std::sync::Barrier;
use std::time::{Duration, Instant};
use tch::{Kind, Tensor};

const ROLE: &str = "BWM_DIST_TEST_ROLE";

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// Runs `f` on every rank of a fresh job, one thread per rank; results in rank order.
fn on_ranks<T: Send>(world: usize, timeout: Duration, f: impl Fn(TcpCollective) -> T + Sync) -> Vec<T> {
    let master = format!("127.0.0.1:{}", free_port());
    std::thread::scope(|s| {
        let handles: Vec<_> = (0..world)
            .map(|rank| {
                let (f, master) = (&f, &master);
                s.spawn(move || f(TcpCollective::new(rank, world, master, timeout).unwrap()))
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    })
}

/// Rank `rank`'s input: awkward values (their sums round) that differ by rank.
fn input(kind: Kind, rank: usize, n: usize) -> Tensor {
    let v: Vec<f64> = (0..n).map(|i| ((i * 37 + rank * 101) % 1000) as f64 / 7.0 - 50.0 + rank as f64 * 1e-3).collect();
    Tensor::from_slice(&v).to_kind(kind)
}

/// Elementwise sum (or mean) over ranks in rank order: f64 for f64 inputs, else f32 rounded once.
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

/// Bit patterns of the values (f64 bits for f64, f32 bits otherwise: exact for bf16 and f16).
fn bits(t: &Tensor) -> Vec<u64> {
    let flat = t.reshape([-1]);
    if t.kind() == Kind::Double {
        Vec::<f64>::try_from(&flat).unwrap().iter().map(|x| x.to_bits()).collect()
    } else {
        Vec::<f32>::try_from(&flat).unwrap().iter().map(|x| x.to_bits() as u64).collect()
    }
}

fn assert_bits(got: &Tensor, want: &Tensor, what: &str) {
    assert_eq!(got.kind(), want.kind(), "{what}: dtype");
    assert_eq!(got.size(), want.size(), "{what}: shape");
    assert!(bits(got) == bits(want), "{what}: values differ\n got {got}\nwant {want}");
}

const KINDS: [Kind; 4] = [Kind::Float, Kind::BFloat16, Kind::Half, Kind::Double];
const N: usize = 12;

/// Every operation on every dtype; the outputs in a fixed order.
fn run_all_ops(c: &mut impl Collective) -> Vec<Tensor> {
    let (rank, world) = (c.rank(), c.world_size());
    let mut out = Vec::new();
    for kind in KINDS {
        let mut t = input(kind, rank, N);
        c.all_reduce_sum(&mut t).unwrap();
        out.push(t);
        let mut t = input(kind, rank, N);
        c.all_reduce_mean(&mut t).unwrap();
        out.push(t);
        let full = input(kind, rank, world * N);
        let mut shard = Tensor::zeros([N as i64], (kind, tch::Device::Cpu));
        c.reduce_scatter_sum(&full, &mut shard).unwrap();
        out.push(shard);
        let mut gathered = Tensor::zeros([world as i64, N as i64], (kind, tch::Device::Cpu));
        c.all_gather(&input(kind, rank, N), &mut gathered).unwrap();
        out.push(gathered);
        for root in [0, world - 1] {
            let mut t = input(kind, rank, N);
            c.broadcast(&mut t, root).unwrap();
            out.push(t);
        }
        c.barrier().unwrap();
    }
    out
}

fn expected_ops(rank: usize, world: usize) -> Vec<Tensor> {
    let mut out = Vec::new();
    for kind in KINDS {
        out.push(expected_reduce(kind, world, N, false));
        out.push(expected_reduce(kind, world, N, true));
        out.push(expected_reduce(kind, world, world * N, false).narrow(0, (rank * N) as i64, N as i64));
        out.push(Tensor::stack(&(0..world).map(|r| input(kind, r, N)).collect::<Vec<_>>(), 0));
        for root in [0, world - 1] {
            out.push(input(kind, root, N));
        }
    }
    out
}

fn check_all_ops(results: &[Vec<Tensor>]) {
    let world = results.len();
    for (rank, got) in results.iter().enumerate() {
        let want = expected_ops(rank, world);
        assert_eq!(got.len(), want.len());
        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
            assert_bits(g, w, &format!("world {world}, rank {rank}, output {i}"));
        }
    }
    for got in &results[1..] {
        for (i, (a, b)) in results[0].iter().zip(got).enumerate() {
            if i % 6 != 2 {
                assert!(bits(a) == bits(b), "output {i} differs between ranks");
            }
        }
    }
}

#[test]
fn every_op_gives_exact_values_on_2_and_3_ranks() {
    for world in [2, 3] {
        let results = on_ranks(world, Duration::from_secs(30), |mut c| run_all_ops(&mut c));
        check_all_ops(&results);
    }
}

#[test]
fn started_reductions_sum_into_the_root_or_every_rank() {
    for world in [2, 3] {
        let roots = [Some(0), Some(world - 1), None];
        let results = on_ranks(world, Duration::from_secs(30), |mut c| {
            let mut out = Vec::new();
            for root in roots {
                let t = input(Kind::Float, c.rank(), N);
                // A slice of a larger buffer, as the optimizer passes its gradient pieces.
                let buffer = Tensor::cat(&[Tensor::zeros([3], (Kind::Float, tch::Device::Cpu)), t], 0);
                c.start_reduce_sum(&buffer.narrow(0, 3, N as i64), root).unwrap();
                c.finish_started().unwrap();
                out.push(buffer.narrow(0, 3, N as i64));
            }
            let err = c.start_reduce_sum(&input(Kind::Float, 0, N), Some(world)).unwrap_err();
            assert!(format!("{err:#}").contains("root"), "{err:#}");
            assert!(c.take_collective_seconds() > 0.0);
            out
        });
        for (rank, got) in results.iter().enumerate() {
            for (root, g) in roots.iter().zip(got) {
                let want = if root.is_none_or(|r| r == rank) { expected_reduce(Kind::Float, world, N, false) } else { input(Kind::Float, rank, N) };
                assert_bits(g, &want, &format!("world {world}, rank {rank}, root {root:?}"));
            }
        }
    }
}

#[test]
fn two_ranks_sum_to_exactly_a_plus_b_and_bf16_rounds_once() {
    let results = on_ranks(2, Duration::from_secs(30), |mut c| {
        let mut t = input(Kind::Float, c.rank(), 1000);
        c.all_reduce_sum(&mut t).unwrap();
        t
    });
    let (a, b) = (Vec::<f32>::try_from(&input(Kind::Float, 0, 1000)).unwrap(), Vec::<f32>::try_from(&input(Kind::Float, 1, 1000)).unwrap());
    let want: Vec<f32> = a.iter().zip(&b).map(|(a, b)| a + b).collect();
    for r in &results {
        assert!(Vec::<f32>::try_from(r).unwrap().iter().zip(&want).all(|(g, w)| g.to_bits() == w.to_bits()));
    }
    // 1 + 2^-8 + 2^-8: summed in bf16 step by step each addition ties to even and stays 1.0; summed
    // in f32 and rounded once it is 1 + 2^-7, which bf16 represents.
    let results = on_ranks(3, Duration::from_secs(30), |mut c| {
        let v = if c.rank() == 0 { 1.0 } else { 1.0 / 256.0 };
        let mut t = Tensor::from_slice(&[v as f32]).to_kind(Kind::BFloat16);
        c.all_reduce_sum(&mut t).unwrap();
        t.to_kind(Kind::Float).double_value(&[0])
    });
    assert_eq!(results, vec![1.0 + 1.0 / 128.0; 3]);
}

#[test]
fn views_parameters_and_integers() {
    let results = on_ranks(2, Duration::from_secs(30), |mut c| {
        let r = c.rank() as f64;
        // A transposed view is updated in place, and so is the tensor it views.
        let base = Tensor::arange(6, (Kind::Float, tch::Device::Cpu)).reshape([2, 3]) + r;
        let mut view = base.tr();
        c.all_reduce_sum(&mut view).unwrap();
        // A parameter that requires grad can be broadcast into.
        let mut p = (Tensor::ones([3], (Kind::Float, tch::Device::Cpu)) * (r + 1.0)).set_requires_grad(true);
        c.broadcast(&mut p, 1).unwrap();
        let mut counts = Tensor::from_slice(&[c.rank() as i64 + 1, 10]);
        c.all_reduce_sum(&mut counts).unwrap();
        let mut mean_of_ints = Tensor::from_slice(&[1i64]);
        let err = c.all_reduce_mean(&mut mean_of_ints).unwrap_err();
        (base, p.detach(), counts, format!("{err:#}"))
    });
    for (base, p, counts, err) in results {
        let want = Tensor::arange(6, (Kind::Float, tch::Device::Cpu)).reshape([2, 3]) * 2.0 + 1.0;
        assert_bits(&base, &want, "all_reduce through a transposed view");
        assert_bits(&p, &Tensor::full([3], 2.0, (Kind::Float, tch::Device::Cpu)), "broadcast into a parameter");
        assert_eq!(Vec::<i64>::try_from(&counts).unwrap(), vec![3, 20]);
        assert!(err.contains("floating-point"), "{err}");
    }
}

#[test]
fn mismatched_calls_are_reported_on_every_rank() {
    let all_done = Barrier::new(2);
    let results = on_ranks(2, Duration::from_secs(30), |mut c| {
        let n = 4 + c.rank() as i64;
        let mut t = Tensor::zeros([n], (Kind::Float, tch::Device::Cpu));
        let start = Instant::now();
        let err = c.all_reduce_sum(&mut t).err().map(|e| format!("{e:#}")).unwrap_or_default();
        let later = c.barrier().err().map(|e| format!("{e:#}")).unwrap_or_default();
        all_done.wait();
        (err, later, start.elapsed())
    });
    for (err, later, took) in results {
        assert!(err.contains("collective mismatch") && err.contains("all_reduce_sum of 4 x Float") && err.contains("5 x Float"), "{err}");
        assert!(later.contains("failed earlier"), "{later}");
        println!("failed after {took:.2?}");
    }
}

#[test]
fn a_rank_that_does_not_join_is_named_within_the_timeout() {
    let timeout = Duration::from_secs(2);
    // Rank 2 starts only once ranks 0 and 1 have given up: ordered by a barrier, not by sleeping.
    let (gave_up, all_done) = (Barrier::new(3), Barrier::new(3));
    let results = on_ranks(3, timeout, |mut c| {
        if c.rank() == 2 {
            gave_up.wait();
        }
        let start = Instant::now();
        let mut t = Tensor::ones([8], (Kind::Float, tch::Device::Cpu));
        let err = c.all_reduce_sum(&mut t).err().map(|e| format!("{e:#}")).unwrap_or_default();
        let took = start.elapsed();
        if c.rank() < 2 {
            gave_up.wait();
        }
        let later = c.barrier().err().map(|e| format!("{e:#}")).unwrap_or_default();
        all_done.wait();
        (err, took, later)
    });
    for (rank, (err, took, later)) in results.iter().enumerate() {
        println!("rank {rank} after {took:.2?}: {err}");
        assert!(err.contains("all_reduce_sum (op #1)"), "rank {rank}: {err}");
        assert!(err.contains("rank(s) 2 did not join"), "rank {rank}: {err}");
        if rank < 2 {
            // A timeout never fires early (the deadline may start a little before `start`).
            assert!(*took >= timeout - Duration::from_millis(500), "rank {rank} took {took:?}");
        }
        assert!(later.contains("failed earlier"), "rank {rank}: {later}");
    }
    assert!(results[1].0.contains("rank 0 reports"), "{}", results[1].0);
}

#[test]
fn a_rank_blocked_sending_to_rank_0_still_gets_the_diagnosis() {
    // Rank 0 reads rank 1 (which never comes) first, so rank 2's 32 MiB request cannot be sent
    // in full; rank 2 must still receive rank 0's verdict before its own timeout.
    let timeout = Duration::from_secs(2);
    // Rank 1 stays connected without joining until the others have their verdicts.
    let (others_done, all_done) = (Barrier::new(3), Barrier::new(3));
    let results = on_ranks(3, timeout, |mut c| {
        let outcome = if c.rank() == 1 {
            others_done.wait();
            String::new()
        } else {
            let mut t = Tensor::ones([8 << 20], (Kind::Float, tch::Device::Cpu));
            let err = c.all_reduce_sum(&mut t).err().map(|e| format!("{e:#}")).unwrap_or_default();
            others_done.wait();
            err
        };
        all_done.wait();
        outcome
    });
    for err in [&results[0], &results[2]] {
        assert!(err.contains("all_reduce_sum (op #1)") && err.contains("rank(s) 1 did not join"), "{err}");
    }
    assert!(results[2].contains("rank 0 reports"), "{}", results[2]);
}

#[test]
fn a_late_rank_0_learns_why_the_others_gave_up() {
    let timeout = Duration::from_secs(1);
    // Rank 0 arrives only after rank 1 has timed out: ordered by a barrier, not by sleeping.
    let (gave_up, all_done) = (Barrier::new(2), Barrier::new(2));
    let results = on_ranks(2, timeout, |mut c| {
        if c.rank() == 0 {
            gave_up.wait();
        }
        let err = c.barrier().err().map(|e| format!("{e:#}")).unwrap_or_default();
        if c.rank() == 1 {
            gave_up.wait();
        }
        all_done.wait();
        err
    });
    // The late rank 0 is told why rather than waiting out a timeout of its own.
    let late = &results[0];
    assert!(late.contains("barrier") && late.contains("rank 1 failed") && late.contains("no reply from rank 0"), "{late}");
    assert!(results[1].contains("barrier (op #1) timed out") && results[1].contains("no reply from rank 0"), "{}", results[1]);
}

#[test]
fn a_rank_that_exits_without_participating_fails_the_others_at_once() {
    // Rank 1 leaves after the rendezvous: rank 0 sees its connection close.
    let results = on_ranks(2, Duration::from_secs(30), |mut c| {
        if c.rank() == 1 {
            return None;
        }
        let start = Instant::now();
        let err = c.all_gather(&Tensor::ones([2], (Kind::Float, tch::Device::Cpu)), &mut Tensor::zeros([4], (Kind::Float, tch::Device::Cpu))).unwrap_err();
        Some((format!("{err:#}"), start.elapsed()))
    });
    let (err, took) = results[0].clone().unwrap();
    assert!(err.contains("all_gather (op #1): rank 1") && err.contains("probably exited"), "{err}");
    println!("failed after {took:.2?}");
    // Rank 0 leaves: the others see theirs close.
    let results = on_ranks(3, Duration::from_secs(30), |mut c| {
        if c.rank() == 0 {
            return None;
        }
        let start = Instant::now();
        let err = c.barrier().unwrap_err();
        Some((format!("{err:#}"), start.elapsed()))
    });
    for (err, took) in results.into_iter().flatten() {
        assert!(err.contains("barrier (op #1) on rank") && err.contains("rank 0") && err.contains("probably exited"), "{err}");
        println!("failed after {took:.2?}");
    }
}

fn spawn_rank(role: &str, rank: usize, world: usize, port: u16) -> Child {
    Command::new(std::env::current_exe().unwrap())
        .args(["--exact", "child_process", "--nocapture", "--test-threads=1"])
        .env(ROLE, role)
        .env("RANK", rank.to_string())
        .env("WORLD_SIZE", world.to_string())
        .env("LOCAL_RANK", rank.to_string())
        .env("MASTER_ADDR", "127.0.0.1")
        .env("MASTER_PORT", port.to_string())
        .env("BWM_DIST_TIMEOUT", "30")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

fn expect_success(child: Child, what: &str) {
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "{what} failed ({}):\n{}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

const BIG: i64 = 16 << 20;

/// Entry point of the child processes (a no-op unless `BWM_DIST_TEST_ROLE` is set).
#[test]
fn child_process() {
    let Ok(role) = std::env::var(ROLE) else { return };
    let mut c = TcpCollective::from_env().unwrap();
    match role.as_str() {
        "ops" => {
            let got = run_all_ops(&mut c);
            let want = expected_ops(c.rank(), c.world_size());
            for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                assert_bits(g, w, &format!("process rank {}, output {i}", c.rank()));
            }
            c.barrier().unwrap();
        }
        "killed" => {
            c.barrier().unwrap();
            // Blocks sending 64 MiB to rank 0, which is not reading, until the parent kills us.
            let mut t = Tensor::ones([BIG], (Kind::Float, tch::Device::Cpu));
            c.all_reduce_sum(&mut t).unwrap();
            unreachable!("rank 0 never completes this all-reduce");
        }
        other => panic!("unknown role {other}"),
    }
}

#[test]
fn three_processes_give_exact_values() {
    let port = free_port();
    let children: Vec<Child> = (0..3).map(|r| spawn_rank("ops", r, 3, port)).collect();
    for (r, child) in children.into_iter().enumerate() {
        expect_success(child, &format!("rank {r}"));
    }
}

#[test]
fn a_process_killed_mid_collective_is_an_error_not_a_hang() {
    let port = free_port();
    let mut child = spawn_rank("killed", 1, 2, port);
    let mut c = TcpCollective::new(0, 2, &format!("127.0.0.1:{port}"), Duration::from_secs(30)).unwrap();
    c.barrier().unwrap();
    std::thread::sleep(Duration::from_millis(500));
    child.kill().unwrap();
    child.wait().unwrap();
    let start = Instant::now();
    let mut t = Tensor::ones([BIG], (Kind::Float, tch::Device::Cpu));
    let err = format!("{:#}", c.all_reduce_sum(&mut t).unwrap_err());
    println!("rank 0 after {:.2?}: {err}", start.elapsed());
    assert!(err.contains("all_reduce_sum (op #2): rank 1") && err.contains("probably exited"), "{err}");
}
