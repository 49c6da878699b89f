// A custom backward needs torch::autograd::Function, which neither tch nor torch-sys's C API exposes.
fn main() {
    bwm_libtorch_cc::compile("src/fp8_linear.cpp", "bwm_fp8_autograd");
}
