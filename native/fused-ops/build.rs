// A custom backward needs torch::autograd::Function (C++ only), and the kernels must run on
// libtorch's current CUDA stream, which only its C++ API reports. Without libtorch_cuda (a
// CPU-only libtorch) the shim is built without the stream.
include!("../../scripts/link_torch_cuda.rs");

fn main() {
    bwm_libtorch_cc::compile_cuda_shim("src/ops.cpp", "bwm_fused_ops");
    // This crate's own test binary (its GPU tests) needs libtorch's CUDA backend loaded.
    link_torch_cuda();
}
