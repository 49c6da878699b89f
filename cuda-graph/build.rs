// at::cuda::CUDAGraph and libtorch's stream guards are C++ only (neither tch nor torch-sys's C API
// has them). Without libtorch_cuda (a CPU-only libtorch) the shim is built to report that instead.
fn main() {
    let lib = std::env::var("DEP_TCH_LIBTORCH_LIB").expect("torch-sys did not report its libtorch (DEP_TCH_LIBTORCH_LIB)");
    let dir = std::path::Path::new(&lib);
    let cuda = bwm_libtorch_cc::cuda_include(dir).filter(|_| dir.join("libtorch_cuda.so").exists());
    bwm_libtorch_cc::compile_with("src/graph.cpp", "bwm_cuda_graph", cuda.as_deref(), if cuda.is_some() { &["BWM_CUDA"] } else { &[] });
    if cuda.is_some() {
        println!("cargo:rustc-link-search=native={lib}");
        println!("cargo:rustc-link-lib=dylib=torch_cuda");
        println!("cargo:rustc-link-lib=dylib=c10_cuda");
    }
}
