// Compiles src/fp8_linear.cpp against the headers of the libtorch torch-sys links (its lib
// folder's sibling `include`): a custom backward needs torch::autograd::Function, which neither
// tch nor torch-sys's C API exposes.
fn main() {
    println!("cargo:rerun-if-changed=src/fp8_linear.cpp");
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    let lib = std::env::var("DEP_TCH_LIBTORCH_LIB").expect("torch-sys did not report its libtorch (DEP_TCH_LIBTORCH_LIB)");
    let root = std::path::Path::new(&lib).parent().expect("libtorch lib folder has a parent").to_path_buf();
    cc::Build::new()
        .cpp(true)
        .file("src/fp8_linear.cpp")
        .include(root.join("include"))
        .include(root.join("include/torch/csrc/api/include"))
        .flag("-std=c++17")
        .flag("-D_GLIBCXX_USE_CXX11_ABI=1")
        .warnings(false)
        .compile("bwm_fp8_autograd");
}
