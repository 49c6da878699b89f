//! `bwm train-light-decoder` end to end on CPU: a light decoder fitted to a small random VAE's
//! decoder on the bundled demo episodes, written with its held-out agreement, then selected by
//! `bwm rollout --light-decoder` in place of the VAE's decoder, and one of random weights timed by
//! `bwm bench-rollout --random-light-decoder`; widths it cannot build, and a file that is not a
//! light decoder, refused with the flag named.

mod common;

use std::process::{Command, Output};

use common::{bwm, demo_data, temp_dir, tiny_world_model, write_random_vae};

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

#[test]
fn a_light_decoder_is_trained_for_a_vae_and_decodes_a_rollout() {
    let dir = temp_dir("light-decoder-cli");
    let vae = dir.join("vae.safetensors");
    write_random_vae(&vae, 5);
    let data = demo_data();
    let light = dir.join("light.safetensors");
    let train = |widths: &str, out: &std::path::Path| {
        Command::new(bwm())
            .args(["train-light-decoder", "--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--max-episodes", "1"])
            .args(["--resolution", "64x32", "--widths", widths, "--blocks", "1", "--clip-frames", "5", "--steps", "3", "--batch", "1"])
            .args(["--device", "cpu", "--out", out.to_str().unwrap()])
            .output()
            .unwrap()
    };
    let o = train("8,8,4,4", &light);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("held-out PSNR against the VAE's decoded frames"), "{}", text(&o));
    assert!(light.is_file() && !dir.join("light.safetensors.tmp").exists());

    let generated = dir.join("generated");
    let rollout = |decoder: &std::path::Path, out: &std::path::Path| {
        tiny_world_model(
            "rollout",
            &["--max-frames", "9", "--episodes", "0", "--frame-storage", "image", "--vae", vae.to_str().unwrap(), "--light-decoder",
              decoder.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap()],
        )
    };
    let o = rollout(&light, &generated);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("decoder: the light decoder"), "{}", text(&o));

    // bench-rollout times a light decoder of random weights and says which decoder it timed.
    let o = Command::new(bwm())
        .args(["bench-rollout", "--random-weights", "tiny", "--vae", vae.to_str().unwrap(), "--random-light-decoder", "--device", "cpu"])
        .args(["--height", "32", "--width", "32", "--history", "4", "--future", "4", "--sample-steps", "2", "--chunks", "1"])
        .output()
        .unwrap();
    assert!(o.status.success() && text(&o).contains("decoded by the light decoder") && text(&o).contains("chunk 0:"), "{}", text(&o));

    // Widths it cannot build and a VAE given as the light decoder: refused, naming the flag.
    let bad = dir.join("bad.safetensors");
    let o = train("8,8,4", &bad);
    assert!(!o.status.success() && text(&o).contains("--widths takes 4 numbers"), "{}", text(&o));
    assert!(!bad.exists() && !text(&o).contains("panicked"));
    let o = rollout(&vae, &dir.join("generated-bad"));
    assert!(!o.status.success() && text(&o).contains("--light-decoder") && text(&o).contains("is not a light decoder"), "{}", text(&o));
    assert!(!text(&o).contains("panicked"));
}
