//! For build scripts of crates that reach libtorch's C++ API where neither tch nor torch-sys's C
//! API does. Such a crate depends on `torch-sys` (which reports its libtorch to dependents' build
//! scripts as `DEP_TCH_LIBTORCH_LIB`) and lists this crate under `[build-dependencies]`.

use std::path::{Path, PathBuf};

/// Compiles `source` (relative to the crate being built) into the static library `name`, against
/// the headers beside the lib folder of the libtorch torch-sys links and this crate's own
/// (`include/bwm_guarded.h`: the shims' exception-to-message guard).
pub fn compile(source: &str, name: &str) {
    compile_with(source, name, None, &[]);
}

/// [`compile`] with one more include folder (e.g. CUDA's, from [`cuda_include`]) and preprocessor
/// symbols defined.
pub fn compile_with(source: &str, name: &str, include: Option<&Path>, defines: &[&str]) {
    println!("cargo:rerun-if-changed={source}");
    let own = Path::new(env!("CARGO_MANIFEST_DIR")).join("include");
    println!("cargo:rerun-if-changed={}", own.join("bwm_guarded.h").display());
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    let lib = std::env::var("DEP_TCH_LIBTORCH_LIB").expect("torch-sys did not report its libtorch (DEP_TCH_LIBTORCH_LIB)");
    let root = Path::new(&lib).parent().expect("libtorch lib folder has a parent");
    let mut build = cc::Build::new();
    build
        .cpp(true)
        .file(source)
        .include(root.join("include"))
        .include(root.join("include/torch/csrc/api/include"))
        .include(&own)
        .flag("-std=c++17")
        .flag("-D_GLIBCXX_USE_CXX11_ABI=1")
        .warnings(false);
    if let Some(dir) = include {
        build.include(dir);
    }
    for d in defines {
        build.define(d, None);
    }
    build.compile(name);
}

/// [`compile_with`] for a shim that reaches libtorch's CUDA API where the libtorch torch-sys links
/// has it (`libtorch_cuda.so` and CUDA's headers, [`cuda_include`]): compiled with `BWM_CUDA`
/// defined and linked against `torch_cuda` and `c10_cuda`. Without them (a CPU-only libtorch) it
/// is compiled without `BWM_CUDA`, for the shim to report that. Returns whether CUDA is in.
pub fn compile_cuda_shim(source: &str, name: &str) -> bool {
    let lib = std::env::var("DEP_TCH_LIBTORCH_LIB").expect("torch-sys did not report its libtorch (DEP_TCH_LIBTORCH_LIB)");
    let dir = Path::new(&lib);
    let cuda = cuda_include(dir).filter(|_| dir.join("libtorch_cuda.so").exists());
    compile_with(source, name, cuda.as_deref(), if cuda.is_some() { &["BWM_CUDA"] } else { &[] });
    if cuda.is_some() {
        println!("cargo:rustc-link-search=native={lib}");
        println!("cargo:rustc-link-lib=dylib=torch_cuda");
        println!("cargo:rustc-link-lib=dylib=c10_cuda");
    }
    cuda.is_some()
}

/// The folder holding CUDA's runtime headers (`cuda_runtime_api.h` and the `crt/` headers it
/// includes) for the libtorch in `lib`: `$CUDA_HOME/include`, else the wheels beside a PyPI torch
/// (`nvidia/cu13/include` or, for CUDA 12, `nvidia/cuda_runtime/include`, when they hold `crt/`;
/// else triton's copy, `triton/backends/nvidia/include`), else `/usr/local/cuda/include`.
pub fn cuda_include(lib: &Path) -> Option<PathBuf> {
    println!("cargo:rerun-if-env-changed=CUDA_HOME");
    let site = lib.parent().and_then(Path::parent);
    let wheels = site.into_iter().flat_map(|s| {
        ["nvidia/cu13/include", "nvidia/cuda_runtime/include", "triton/backends/nvidia/include"].map(|p| s.join(p))
    });
    std::env::var_os("CUDA_HOME")
        .map(|h| PathBuf::from(h).join("include"))
        .into_iter()
        .chain(wheels)
        .chain([PathBuf::from("/usr/local/cuda/include")])
        .find(|d| d.join("cuda_runtime_api.h").exists() && d.join("crt/host_config.h").exists())
}
