// The backend switches are methods of at::Context, which neither tch nor torch-sys's C API exposes.
fn main() {
    bwm_libtorch_cc::compile("src/sdp.cpp", "bwm_sdp");
}
