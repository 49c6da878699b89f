// A custom backward needs torch::autograd::Function, which neither tch nor torch-sys's C API
// exposes, and the quantization pass must run on libtorch's current CUDA stream, which only its C++
// API reports. Without libtorch_cuda (a CPU-only libtorch) the shim is built without the stream.
include!("../../scripts/link_torch_cuda.rs");

fn main() {
    bwm_libtorch_cc::compile_cuda_shim("src/fp8_linear.cpp", "bwm_fp8_autograd");
    // This crate's own test binary (its GPU test) needs libtorch's CUDA backend loaded.
    link_torch_cuda();
}
