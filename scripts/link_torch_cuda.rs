// Shared by the build scripts of the crates that produce executables (`include!`d).
// The linker drops libtorch_cuda.so because no symbol of it is named, and CUDA is then silently
// unavailable; --no-as-needed keeps it. The rpath lets binaries run here without LD_LIBRARY_PATH
// (which still takes precedence on the GPU machines, where torch lives elsewhere).
fn link_torch_cuda() {
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    let Ok(lib) = std::env::var("DEP_TCH_LIBTORCH_LIB") else { return };
    let dir = std::path::Path::new(&lib);
    println!("cargo:rustc-link-arg=-Wl,-rpath,{}", dir.display());
    if dir.join("libtorch_cuda.so").exists() {
        println!("cargo:rustc-link-arg=-Wl,--no-as-needed");
        println!("cargo:rustc-link-arg=-ltorch_cuda");
        println!("cargo:rustc-link-arg=-Wl,--as-needed");
    }
}
