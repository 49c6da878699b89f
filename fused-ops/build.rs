// A custom backward needs torch::autograd::Function (C++ only), and the kernel must run on
// libtorch's current CUDA stream, which only its C++ API reports. Without libtorch_cuda (a
// CPU-only libtorch) the shim is built without the stream.
include!("../scripts/link_torch_cuda.rs");

fn main() {
    let lib = std::env::var("DEP_TCH_LIBTORCH_LIB").expect("torch-sys did not report its libtorch (DEP_TCH_LIBTORCH_LIB)");
    let dir = std::path::Path::new(&lib);
    let cuda = bwm_libtorch_cc::cuda_include(dir).filter(|_| dir.join("libtorch_cuda.so").exists());
    bwm_libtorch_cc::compile_with("src/ops.cpp", "bwm_fused_ops", cuda.as_deref(), if cuda.is_some() { &["BWM_CUDA"] } else { &[] });
    if cuda.is_some() {
        println!("cargo:rustc-link-search=native={lib}");
        println!("cargo:rustc-link-lib=dylib=c10_cuda");
    }
    // This crate's own test binary (its GPU test) needs libtorch's CUDA backend loaded.
    link_torch_cuda();
}
