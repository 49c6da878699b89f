// libtorch's profiler (torch/csrc/autograd/profiler_kineto.h) is C++ only: neither tch nor
// torch-sys's C API reaches it.
fn main() {
    bwm_libtorch_cc::compile("src/profiler.cpp", "bwm_profiler");
}
