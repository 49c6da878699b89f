//! Test folders are removed when their guard drops, also when the test panics, and the process's
//! folder with whatever is left in it when the process exits.

use std::process::Command;

use bwm_testdir::{root, shared_dir, TestDir};

#[test]
fn a_test_dir_is_removed_when_dropped_and_when_its_test_panics() {
    let dir = TestDir::new("dropped");
    std::fs::write(dir.join("file"), "x").unwrap();
    std::fs::create_dir_all(dir.join("a/b")).unwrap();
    let path = dir.to_path_buf();
    assert!(path.starts_with(root()) && path.file_name().unwrap().to_str().unwrap().starts_with("dropped-"), "{path:?}");
    drop(dir);
    assert!(!path.exists(), "{path:?} is left");

    let (tx, rx) = std::sync::mpsc::channel();
    let panicked = std::thread::spawn(move || {
        let dir = TestDir::new("panics");
        std::fs::write(dir.join("file"), "x").unwrap();
        tx.send(dir.to_path_buf()).unwrap();
        panic!("a failing test");
    })
    .join();
    assert!(panicked.is_err());
    let path = rx.recv().unwrap();
    assert!(!path.exists(), "{path:?} is left");
}

#[test]
fn two_test_dirs_of_one_name_differ() {
    let (a, b) = (TestDir::new("same"), TestDir::new("same"));
    assert_ne!(a.path(), b.path());
}

/// Run by `the_process_folder_is_removed_at_exit` in a child process.
#[test]
fn child_leaves_folders_behind() {
    if std::env::var_os("BWM_TESTDIR_CHILD").is_none() {
        return;
    }
    let kept = TestDir::new("kept");
    std::fs::write(shared_dir("shared").join("file"), "x").unwrap();
    println!("root={}", root().display());
    std::mem::forget(kept);
}

#[test]
fn the_process_folder_is_removed_at_exit() {
    let out = Command::new(std::env::current_exe().unwrap())
        .args(["--exact", "child_leaves_folders_behind", "--nocapture", "--test-threads=1"])
        .env("BWM_TESTDIR_CHILD", "1")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    let child_root = stdout.lines().find_map(|l| l.split_once("root=").map(|(_, r)| r.trim())).unwrap_or_else(|| panic!("{stdout}"));
    assert_ne!(std::path::Path::new(child_root), root());
    assert!(!std::path::Path::new(child_root).exists(), "{child_root} is left");
}
