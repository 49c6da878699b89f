//! `bwm train-vae` end to end on the bundled demo episodes in bf16 (fp32 masters) with the L1
//! loss and 8 latent channels: an f32 file that `bwm reconstruct` reads; and a dtype it cannot
//! train in, a loss it does not know, the removed motion loss or its weight, or no latent channel
//! refused before any decoding.

mod common;

use std::process::Command;

use common::*;
use tch::Kind;

#[test]
fn train_vae_trains_in_bf16_and_writes_an_f32_vae() {
    let dir = temp_dir("train-vae-bf16");
    let out = dir.join("vae.safetensors");
    let run = |dtype: &str, loss: &str, z_dim: &str, out: &std::path::Path| {
        Command::new(bwm())
            .args(["train-vae", "--data", demo_data().to_str().unwrap(), "--max-episodes", "1", "--resolution", "32x32"])
            .args(["--dim", "4", "--dec-dim", "4", "--clip-frames", "5", "--steps", "2", "--batch", "1", "--device", "cpu"])
            .args(["--dtype", dtype, "--recon-loss", loss, "--z-dim", z_dim, "--out", out.to_str().unwrap()])
            .output()
            .unwrap()
    };
    let o = run("bf16", "l1", "8", &out);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&o.stderr));
    assert!(stdout.contains("in bf16, l1 loss") && stdout.contains("reconstruction PSNR"), "{stdout}");
    let weights = tch::Tensor::read_safetensors(&out).unwrap();
    assert!(!weights.is_empty() && weights.iter().all(|(_, t)| t.kind() == Kind::Float), "the file holds f32 weights");
    let stats = weights.iter().find(|(n, _)| n == "latents_mean").map(|(_, t)| t.size());
    assert_eq!(stats, Some(vec![8]), "one latent statistic per channel");
    let rec = dir.join("rec.safetensors");
    let o = Command::new(bwm())
        .args(["reconstruct", "--data", demo_data().to_str().unwrap(), "--vae", out.to_str().unwrap(), "--max-episodes", "1"])
        .args(["--resolution", "32x32", "--device", "cpu", "--out", rec.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    let bad = dir.join("bad.safetensors");
    let o = run("f16", "mse", "48", &bad);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("--dtype") && stderr.contains("f16"), "{stderr}");
    assert!(!stderr.contains("panicked") && !bad.exists(), "{stderr}");
    let o = run("f32", "lpips", "48", &bad);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("--recon-loss") && stderr.contains("known: mse, l1"), "{stderr}");
    assert!(!stderr.contains("panicked") && !bad.exists(), "{stderr}");
    // The motion loss and its weight were removed (issue 69): refused by name with the reason,
    // before any decoding.
    for (flag, value) in [("--recon-loss", "motion"), ("--motion-weight", "2")] {
        let o = Command::new(bwm())
            .args(["train-vae", "--data", demo_data().to_str().unwrap(), "--max-episodes", "1", "--resolution", "32x32"])
            .args(["--dim", "4", "--dec-dim", "4", "--z-dim", "8", "--clip-frames", "5", "--steps", "2", "--batch", "1", "--device", "cpu"])
            .args([flag, value, "--out", bad.to_str().unwrap()])
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && stderr.contains(flag) && stderr.contains("was removed") && stderr.contains("run 34"), "{flag} {value}: {stderr}");
        assert!(!stderr.contains("panicked") && !bad.exists(), "{stderr}");
    }
    let o = run("f32", "mse", "0", &bad);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("--z-dim") && stderr.contains("must be positive"), "{stderr}");
    assert!(!stderr.contains("panicked") && !bad.exists(), "{stderr}");
}
