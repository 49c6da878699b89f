//! For build scripts of crates that reach libtorch's C++ API where neither tch nor torch-sys's C
//! API does. Such a crate depends on `torch-sys` (which reports its libtorch to dependents' build
//! scripts as `DEP_TCH_LIBTORCH_LIB`) and lists this crate under `[build-dependencies]`.

use std::path::Path;

/// Compiles `source` (relative to the crate being built) into the static library `name`, against
/// the headers beside the lib folder of the libtorch torch-sys links.
pub fn compile(source: &str, name: &str) {
    println!("cargo:rerun-if-changed={source}");
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    let lib = std::env::var("DEP_TCH_LIBTORCH_LIB").expect("torch-sys did not report its libtorch (DEP_TCH_LIBTORCH_LIB)");
    let root = Path::new(&lib).parent().expect("libtorch lib folder has a parent");
    cc::Build::new()
        .cpp(true)
        .file(source)
        .include(root.join("include"))
        .include(root.join("include/torch/csrc/api/include"))
        .flag("-std=c++17")
        .flag("-D_GLIBCXX_USE_CXX11_ABI=1")
        .warnings(false)
        .compile(name);
}
