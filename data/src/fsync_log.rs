//! What this crate's test binary made durable: every `fsync` is recorded with the path of its
//! descriptor. What a crash would keep cannot be observed, so the tests of the writers look at what
//! was synced, and in which order (the bytes under a temporary name, then the folder after the
//! rename).

use std::path::{Path, PathBuf};
use std::sync::Mutex;

static SYNCED: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// Stands in for libc's `fsync` in this test binary (std's `sync_all` calls it): records the
/// descriptor's path, then makes the system call.
#[no_mangle]
extern "C" fn fsync(fd: libc::c_int) -> libc::c_int {
    if let Ok(path) = std::fs::read_link(format!("/proc/self/fd/{fd}")) {
        SYNCED.lock().unwrap_or_else(|e| e.into_inner()).push(path);
    }
    // SAFETY: the fsync system call on the descriptor the caller passed.
    unsafe { libc::syscall(libc::SYS_fsync, fd) as libc::c_int }
}

/// The paths synced so far under `dir`, in order.
pub fn synced_in(dir: &Path) -> Vec<PathBuf> {
    SYNCED.lock().unwrap_or_else(|e| e.into_inner()).iter().filter(|p| p.starts_with(dir)).cloned().collect()
}
