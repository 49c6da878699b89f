//! `bwm reconstruct` end to end on the bundled demo episodes: a random VAE's round trip written
//! per episode, and bad input refused with a one-line error.

mod common;

use std::process::Command;

use common::*;
use tch::{Kind, Tensor};

#[test]
fn reconstruct_writes_every_frame_of_each_episode_and_its_psnr() {
    let dir = temp_dir("reconstruct");
    let vae = dir.join("vae.safetensors");
    write_random_vae(&vae, 3);
    let out = dir.join("out/rec.safetensors");
    let run = |extra: &[&str]| {
        Command::new(bwm())
            .args(["reconstruct", "--data", demo_data().to_str().unwrap(), "--vae", vae.to_str().unwrap(), "--device", "cpu"])
            .args(extra)
            .output()
            .unwrap()
    };
    let o = run(&["--out", out.to_str().unwrap(), "--max-episodes", "2", "--resolution", "64x48"]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&o.stderr));
    assert!(stdout.contains("reconstruct: 2 episodes") && stdout.contains("dB"), "{stdout}");
    let mut named = Tensor::read_safetensors(&out).unwrap();
    named.sort_by(|a, b| a.0.cmp(&b.0));
    assert_eq!(named.len(), 2);
    let manifest = std::fs::read_to_string(demo_data().join("demo.jsonl")).unwrap();
    for (name, t) in &named {
        assert_eq!(t.kind(), Kind::Uint8);
        let s = t.size();
        assert_eq!((s[0], s[2], s[3]), (3, 48, 64), "{name}: {s:?}");
        // Named by the dataset's episode_index, every frame of the episode kept.
        let index = name.strip_prefix("episode.").unwrap_or_else(|| panic!("{name}"));
        let entry = format!("\"episode_index\": {index}, \"length\": {}", s[1]);
        assert!(manifest.contains(&entry), "{name} with {} frames is not an episode of demo.jsonl", s[1]);
    }
    assert!(!dir.join("out/rec.safetensors.partial").exists());

    // A size the VAE's grid does not divide, and a VAE that is not there: one-line errors.
    let o = run(&["--out", dir.join("bad.safetensors").to_str().unwrap(), "--resolution", "60x48"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("60x48"), "{stderr}");
    let o = Command::new(bwm())
        .args(["reconstruct", "--data", demo_data().to_str().unwrap(), "--vae", dir.join("none.safetensors").to_str().unwrap()])
        .args(["--out", dir.join("bad.safetensors").to_str().unwrap(), "--resolution", "64x48", "--device", "cpu"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("none.safetensors"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(!dir.join("bad.safetensors").exists());
}
