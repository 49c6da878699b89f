// at::cuda::CUDAGraph and libtorch's stream guards are C++ only (neither tch nor torch-sys's C API
// has them). Without libtorch_cuda (a CPU-only libtorch) the shim is built to report that instead.
fn main() {
    bwm_libtorch_cc::compile_cuda_shim("src/graph.cpp", "bwm_cuda_graph");
}
