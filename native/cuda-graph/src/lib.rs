//! CUDA graphs for libtorch work of fixed shapes: what a closure launches is recorded once and
//! replayed afterwards with one launch, so a step made of thousands of small kernels no longer
//! pays the host's launch cost for each (at::cuda::CUDAGraph, as `torch.cuda.graph` in Python;
//! tch has no binding, so src/graph.cpp is the shim).
//!
//! A replay reads the tensors the recorded work read, at the same addresses, and writes its
//! outputs into the tensors the capture created: new inputs are copied into the tensors the
//! capture read (`copy_`), and the outputs are read from what the closure returned. The recorded
//! work must not read tensor values on the host (`double_value`, `int64_value`, copies to the
//! CPU) nor take decisions from them, and nothing it reads may be reallocated between replays.
//!
//! [`CudaStream`] runs libtorch work on a stream of its own (libtorch's current stream, which tch
//! cannot set either), so that independent work can be queued beside other work.

use std::ffi::{c_char, c_int, CStr};
use std::panic::{catch_unwind, AssertUnwindSafe};

use anyhow::{anyhow, bail, ensure, Context, Result};
use tch::{Device, Tensor};

#[repr(C)]
struct RawGraph {
    _private: [u8; 0],
}

#[repr(C)]
struct RawStream {
    _private: [u8; 0],
}

extern "C" {
    fn bwm_graph_error() -> *const c_char;
    fn bwm_graph_new(device: c_int) -> *mut RawGraph;
    fn bwm_graph_enter(g: *mut RawGraph) -> bool;
    fn bwm_graph_leave(g: *mut RawGraph) -> bool;
    fn bwm_graph_capture_begin(g: *mut RawGraph) -> bool;
    fn bwm_graph_capture_end(g: *mut RawGraph) -> bool;
    fn bwm_graph_capture_abort(g: *mut RawGraph);
    fn bwm_graph_replay(g: *mut RawGraph) -> bool;
    fn bwm_graph_free(g: *mut RawGraph);
    fn bwm_stream_new(device: c_int) -> *mut RawStream;
    fn bwm_stream_enter(s: *mut RawStream) -> bool;
    fn bwm_stream_leave(s: *mut RawStream) -> bool;
    fn bwm_stream_free(s: *mut RawStream);
}

fn shim_error(what: &str) -> anyhow::Error {
    // SAFETY: the shim returns a pointer to its thread's NUL-terminated last error message.
    let msg = unsafe { CStr::from_ptr(bwm_graph_error()) }.to_string_lossy().into_owned();
    anyhow!("{what}: {msg}")
}

/// Runs `body`, turning a panic (tch's tensor methods panic on libtorch errors) into an error.
fn run<T>(body: impl FnOnce() -> Result<T>) -> Result<T> {
    catch_unwind(AssertUnwindSafe(body)).unwrap_or_else(|p| {
        let msg = p.downcast_ref::<String>().cloned().or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()));
        Err(anyhow!("{}", msg.unwrap_or_else(|| "panicked".into())))
    })
}

/// `body` between the shim's `enter` and `leave` (each false on failure, with the shim's error),
/// its panics caught; `leave` runs also when `body` fails.
fn between<T>(enter: impl FnOnce() -> bool, entering: &str, leave: impl FnOnce() -> bool, leaving: &str, body: impl FnOnce() -> Result<T>) -> Result<T> {
    if !enter() {
        return Err(shim_error(entering));
    }
    let out = run(body);
    let left = leave();
    let out = out?;
    if !left {
        return Err(shim_error(leaving));
    }
    Ok(out)
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    Empty,
    Recorded,
    Failed,
}

/// One recorded piece of work on one CUDA device, with its own stream for warm-up runs and the
/// capture, and its own memory pool (freed with it).
pub struct CudaGraph {
    raw: *mut RawGraph,
    state: State,
}

impl CudaGraph {
    /// An empty graph on `device`; an error on a CPU device or a libtorch without CUDA.
    pub fn new(device: Device) -> Result<Self> {
        let Device::Cuda(index) = device else { bail!("CUDA graphs need a CUDA device, not {device:?}") };
        // SAFETY: the shim allocates a graph object (null and an error message on failure).
        let raw = unsafe { bwm_graph_new(index as c_int) };
        if raw.is_null() {
            return Err(shim_error("creating a CUDA graph"));
        }
        Ok(Self { raw, state: State::Empty })
    }

    /// Runs `body` eagerly on the graph's stream and waits for it. Libraries set up their
    /// per-stream state (cuBLAS workspaces, the autograd engine's streams) on first use, which a
    /// capture cannot do: run the work once or twice this way before [`CudaGraph::capture`].
    pub fn warm_up<T>(&mut self, body: impl FnOnce() -> Result<T>) -> Result<T> {
        between(
            // SAFETY: `raw` is this graph's live object.
            || unsafe { bwm_graph_enter(self.raw) },
            "switching to the graph's stream",
            // SAFETY: as above; leaving restores the stream that was current before.
            || unsafe { bwm_graph_leave(self.raw) },
            "waiting for the graph's stream",
            body,
        )
    }

    /// Records what `body` launches, without running it; [`CudaGraph::replay`] runs it. The
    /// tensors `body` returns live in the graph's memory and hold each replay's results. A graph
    /// records once; a failed capture leaves it unusable.
    pub fn capture<T>(&mut self, body: impl FnOnce() -> Result<T>) -> Result<T> {
        if self.state != State::Empty {
            bail!("this CUDA graph has already been captured");
        }
        // SAFETY: `raw` is this graph's live object.
        if !unsafe { bwm_graph_capture_begin(self.raw) } {
            self.state = State::Failed;
            return Err(shim_error("starting a CUDA graph capture"));
        }
        match run(body) {
            Ok(out) => {
                // SAFETY: as above, with the capture begun.
                if !unsafe { bwm_graph_capture_end(self.raw) } {
                    self.state = State::Failed;
                    return Err(shim_error("ending the CUDA graph capture (did the recorded work read a value on the host?)"));
                }
                self.state = State::Recorded;
                Ok(out)
            }
            Err(e) => {
                // SAFETY: as above; ends the capture the failed body left open.
                unsafe { bwm_graph_capture_abort(self.raw) };
                self.state = State::Failed;
                Err(e.context("recording a CUDA graph (the recorded work must not read values on the host)"))
            }
        }
    }

    /// Launches the recorded work on the current stream, in order with the work queued before it.
    pub fn replay(&self) -> Result<()> {
        if self.state != State::Recorded {
            bail!("replaying a CUDA graph that holds no complete capture");
        }
        // SAFETY: `raw` is this graph's live object, with a complete capture.
        if !unsafe { bwm_graph_replay(self.raw) } {
            return Err(shim_error("replaying a CUDA graph"));
        }
        Ok(())
    }
}

impl Drop for CudaGraph {
    fn drop(&mut self) {
        // SAFETY: `raw` came from `bwm_graph_new` and is freed once, here.
        unsafe { bwm_graph_free(self.raw) };
    }
}

/// A CUDA stream of libtorch's pool. What libtorch launches inside [`CudaStream::scope`] (kernels,
/// copies, and the host's waits for copies to the CPU) is queued on it, in order with itself and
/// beside the work of other streams; tensors made inside one scope should be used inside scopes of
/// the same stream.
pub struct CudaStream {
    raw: *mut RawStream,
}

impl CudaStream {
    /// A stream on `device`; an error on a CPU device or a libtorch without CUDA.
    pub fn new(device: Device) -> Result<Self> {
        let Device::Cuda(index) = device else { bail!("CUDA streams need a CUDA device, not {device:?}") };
        // SAFETY: the shim allocates a stream holder (null and an error message on failure).
        let raw = unsafe { bwm_stream_new(index as c_int) };
        if raw.is_null() {
            return Err(shim_error("taking a CUDA stream"));
        }
        Ok(Self { raw })
    }

    /// Runs `body` with this stream current on its device, then makes the stream and device that
    /// were current before current again (also when `body` fails or panics).
    pub fn scope<T>(&self, body: impl FnOnce() -> Result<T>) -> Result<T> {
        between(
            // SAFETY: `raw` is this stream's live holder.
            || unsafe { bwm_stream_enter(self.raw) },
            "making a CUDA stream current",
            // SAFETY: as above, entered just before.
            || unsafe { bwm_stream_leave(self.raw) },
            "making the CUDA stream before current again",
            body,
        )
    }
}

impl Drop for CudaStream {
    fn drop(&mut self) {
        // SAFETY: `raw` came from `bwm_stream_new` and is freed once, here.
        unsafe { bwm_stream_free(self.raw) };
    }
}

/// A step of fixed shapes run through a [`CudaGraph`]: eager on the graph's stream for the first
/// `warm_ups` calls, recorded on the next and replayed from then on, each call's inputs copied
/// into the tensors the recording read.
pub struct GraphedStep {
    graph: CudaGraph,
    warm_ups_left: u32,
    /// The tensors the recording reads and the one it writes.
    recorded: Option<(Vec<Tensor>, Tensor)>,
}

impl GraphedStep {
    pub fn new(device: Device, warm_ups: u32) -> Result<Self> {
        Ok(Self { graph: CudaGraph::new(device)?, warm_ups_left: warm_ups, recorded: None })
    }

    /// `body` on `inputs` (every tensor it reads that changes from call to call, of the same
    /// shapes each time; anything else it reads must stay where it is), or its recording
    /// replayed on them: what `body` returned, copied out of the graph's memory once recorded.
    pub fn run(&mut self, inputs: &[&Tensor], body: impl FnOnce(&[Tensor]) -> Result<Tensor>) -> Result<Tensor> {
        if self.warm_ups_left > 0 {
            self.warm_ups_left -= 1;
            let inputs: Vec<Tensor> = inputs.iter().map(|t| t.shallow_clone()).collect();
            return self.graph.warm_up(|| body(&inputs)).context("a warm-up run on the CUDA graph's stream");
        }
        match &self.recorded {
            Some((statics, _)) => {
                ensure!(statics.len() == inputs.len(), "a graphed step was given {} inputs, recorded with {}", inputs.len(), statics.len());
                for (i, (dst, src)) in statics.iter().zip(inputs).enumerate() {
                    ensure!(dst.size() == src.size(), "a graphed step's input {i} is {:?}, recorded as {:?}", src.size(), dst.size());
                    tch::no_grad(|| dst.shallow_clone().copy_(src));
                }
            }
            None => {
                let statics: Vec<Tensor> = inputs.iter().map(|t| t.copy()).collect();
                let out = self.graph.capture(|| body(&statics))?;
                self.recorded = Some((statics, out));
            }
        }
        self.graph.replay()?;
        let (_, out) = self.recorded.as_ref().context("the recorded step is missing")?;
        // A copy: the next replay overwrites the recorded output.
        Ok(out.copy())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Kind;

    /// Whether libtorch sees a CUDA device. The tests that need one are ignored by a plain
    /// `cargo test`; run with `--ignored` where none is, they fail when BWM_REQUIRE names cuda (as
    /// scripts/gpu/unit.sh sets it) and are logged as skipped otherwise, never passed.
    fn cuda() -> bool {
        bwm_testdir::need(bwm_testdir::Dep::Cuda, (!tch::Cuda::is_available()).then(|| "libtorch sees no CUDA device".to_string()))
    }

    #[test]
    fn a_cpu_device_is_refused_by_name() {
        let err = CudaGraph::new(Device::Cpu).err().expect("a CPU graph must be refused").to_string();
        assert!(err.contains("CUDA graphs need a CUDA device"), "{err}");
        let err = CudaStream::new(Device::Cpu).err().expect("a CPU stream must be refused").to_string();
        assert!(err.contains("CUDA streams need a CUDA device"), "{err}");
    }

    /// On a CUDA machine: work queued on two streams in turn, each read back inside its own
    /// scope, gives what the same work gives on the default stream; a failing body still leaves
    /// its scope, so the stream before is current again.
    #[test]
    #[ignore = "needs a CUDA device (scripts/gpu/unit.sh)"]
    fn work_on_two_streams_in_turn_gives_the_default_streams_results() {
        if !cuda() {
            return;
        }
        let dev = Device::Cuda(0);
        tch::manual_seed(0);
        let w = Tensor::randn([512, 512], (Kind::Float, dev));
        let inputs: Vec<Tensor> = (0..2).map(|_| Tensor::randn([256, 512], (Kind::Float, dev))).collect();
        tch::Cuda::synchronize(0);
        let work = |x: &Tensor| -> Tensor {
            let mut y = x.shallow_clone();
            for _ in 0..20 {
                y = y.matmul(&w).tanh();
            }
            y
        };
        let want: Vec<Tensor> = inputs.iter().map(|x| work(x).to_device(Device::Cpu)).collect();
        let streams = [CudaStream::new(dev).unwrap(), CudaStream::new(dev).unwrap()];
        // Both queued before either is read, as the pipelined rollouts do.
        let queued: Vec<Tensor> = streams.iter().zip(&inputs).map(|(s, x)| s.scope(|| Ok(work(x))).unwrap()).collect();
        for ((s, y), want) in streams.iter().zip(queued).zip(&want) {
            let got = s.scope(|| Ok(y.to_device(Device::Cpu))).unwrap();
            assert!(got.allclose(want, 1e-5, 1e-6, false), "a stream's result differs from the default stream's");
        }
        let err = streams[0].scope(|| -> Result<()> { bail!("inside") }).unwrap_err();
        assert!(err.to_string().contains("inside"), "{err}");
        let err = streams[0].scope(|| -> Result<()> { panic!("panicked inside") }).unwrap_err();
        assert!(err.to_string().contains("panicked inside"), "{err}");
        // Nested scopes unwind in order, and the default stream works as before.
        let v = streams[0].scope(|| streams[1].scope(|| Ok(work(&inputs[0]).to_device(Device::Cpu)))).unwrap();
        assert!(v.allclose(&want[0], 1e-5, 1e-6, false));
        assert!(work(&inputs[1]).to_device(Device::Cpu).allclose(&want[1], 1e-5, 1e-6, false));
    }

    /// On a CUDA machine: the graph replays the recorded arithmetic and the backward pass on the
    /// inputs copied in since, and matches the same work run eagerly.
    #[test]
    #[ignore = "needs a CUDA device (scripts/gpu/unit.sh)"]
    fn replays_forward_and_backward_on_new_inputs_as_the_eager_run_computes_them() {
        if !cuda() {
            return;
        }
        let dev = Device::Cuda(0);
        tch::manual_seed(0);
        let w = Tensor::randn([64, 64], (Kind::Float, dev)).set_requires_grad(true);
        let x = Tensor::zeros([8, 64], (Kind::Float, dev));
        let step = |x: &Tensor| -> Result<Tensor> {
            let loss = x.matmul(&w).tanh().square().mean(Kind::Float);
            loss.f_backward()?;
            Ok(loss)
        };
        let mut graph = CudaGraph::new(dev).unwrap();
        let inputs: Vec<Tensor> = (0..3).map(|_| Tensor::randn([8, 64], (Kind::Float, dev))).collect();
        let _ = x.shallow_clone().copy_(&inputs[0]);
        let _ = graph.warm_up(|| step(&x)).unwrap();
        let _ = w.grad().zero_();
        let loss = graph.capture(|| step(&x)).unwrap();
        for input in &inputs {
            let _ = x.shallow_clone().copy_(input);
            graph.replay().unwrap();
            let (got_loss, got_grad) = (loss.copy(), w.grad().copy());
            let _ = w.grad().zero_();
            let want_loss = step(input).unwrap();
            let want_grad = w.grad().copy();
            let _ = w.grad().zero_();
            assert!(got_loss.allclose(&want_loss, 1e-6, 1e-7, false), "loss {got_loss:?} vs {want_loss:?}");
            assert!(got_grad.allclose(&want_grad, 1e-5, 1e-7, false), "the replayed gradient differs from the eager one");
        }
    }

    #[test]
    #[ignore = "needs a CUDA device (scripts/gpu/unit.sh)"]
    fn a_graphed_step_warms_up_records_and_replays_on_each_calls_inputs() {
        if !cuda() {
            return;
        }
        let dev = Device::Cuda(0);
        let w = Tensor::randn([64, 64], (Kind::Float, dev));
        let mut step = GraphedStep::new(dev, 1).unwrap();
        let mut outputs = Vec::new();
        for _ in 0..4 {
            let x = Tensor::randn([8, 64], (Kind::Float, dev));
            let got = step.run(&[&x], |t| Ok(t[0].matmul(&w).tanh())).unwrap();
            assert!(got.allclose(&x.matmul(&w).tanh(), 1e-5, 1e-6, false));
            outputs.push(got);
        }
        // Each call's result is its own: the later replays did not overwrite the earlier ones.
        assert!(!outputs[2].allclose(&outputs[3], 1e-3, 1e-3, false));
        let err = step.run(&[&Tensor::zeros([4, 64], (Kind::Float, dev))], |t| Ok(t[0].shallow_clone())).unwrap_err();
        assert!(err.to_string().contains("recorded as"), "{err}");
    }

    #[test]
    #[ignore = "needs a CUDA device (scripts/gpu/unit.sh)"]
    fn a_host_read_inside_the_capture_is_an_error_and_the_graph_cannot_replay() {
        if !cuda() {
            return;
        }
        let dev = Device::Cuda(0);
        let x = Tensor::ones([4], (Kind::Float, dev));
        let mut graph = CudaGraph::new(dev).unwrap();
        let _ = graph.warm_up(|| Ok((&x * 2.0).sum(Kind::Float))).unwrap();
        let err = graph.capture(|| Ok((&x * 2.0).sum(Kind::Float).double_value(&[]))).unwrap_err();
        assert!(format!("{err:#}").contains("must not read values on the host"), "{err:#}");
        assert!(graph.replay().is_err());
        // The device still works after the failed capture.
        assert_eq!((&x * 3.0).sum(Kind::Float).double_value(&[]), 12.0);
    }
}
