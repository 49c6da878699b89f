//! Properties of the VAE that do not need reference numbers: causality, bounded streaming
//! memory, and clear errors on bad input.

mod common;

use bwm_model::vae::{VaeConfig, WanVae};
use common::{rel_err, tmp_dir};
use tch::{Device, Kind, Tensor};

fn small() -> VaeConfig {
    VaeConfig::with_width(8, 8)
}

fn video(frames: i64, h: i64, w: i64, seed: i64) -> Tensor {
    bwm_model::vb::with_seed(seed, || Tensor::rand([1, 3, frames, h, w], (Kind::Float, Device::Cpu))) * 2.0 - 1.0
}

#[test]
fn encoding_is_causal() {
    let (vae, _) = WanVae::random(&small(), Kind::Float, Device::Cpu, 1).unwrap();
    let long = video(13, 32, 48, 2);
    let full = tch::no_grad(|| vae.encode(&long)).unwrap();
    assert_eq!(full.size(), [1, 48, 4, 2, 3]);
    for frames in [1, 5, 9] {
        let prefix = tch::no_grad(|| vae.encode(&long.narrow(2, 0, frames))).unwrap();
        let k = prefix.size()[2];
        // Equal up to float rounding: the final 1x1x1 conv runs over a different number of frames.
        let e = rel_err(&prefix, &full.narrow(2, 0, k));
        assert!(e < 1e-6, "first {frames} frames: rel err {e}");
    }
    // Changing later frames leaves latent 0 (frame 0 alone) untouched.
    let other = Tensor::cat(&[long.narrow(2, 0, 1), video(12, 32, 48, 3)], 2);
    let z = tch::no_grad(|| vae.encode(&other)).unwrap();
    assert!(rel_err(&z.narrow(2, 0, 1), &full.narrow(2, 0, 1)) < 1e-6);
    assert!(rel_err(&z.narrow(2, 1, 1), &full.narrow(2, 1, 1)) > 1e-3);
}

#[test]
fn streaming_decode_memory_does_not_grow_with_length() {
    let (vae, _) = WanVae::random(&small(), Kind::Float, Device::Cpu, 4).unwrap();
    let latents = bwm_model::vb::with_seed(5, || Tensor::randn([1, 48, 24, 2, 3], (Kind::Float, Device::Cpu)));
    let mut stream = vae.decoder_stream();
    let mut frames = Vec::new();
    let mut cache_sizes = Vec::new();
    tch::no_grad(|| {
        for i in 0..24 {
            let out = stream.next(&latents.narrow(2, i, 1)).unwrap();
            assert_eq!(out.size()[2], if i == 0 { 1 } else { 4 });
            frames.push(out);
            cache_sizes.push(stream.cache_bytes());
        }
    });
    assert!(cache_sizes[2..].iter().all(|&b| b == cache_sizes[2]), "cache bytes per chunk: {cache_sizes:?}");
    let streamed = Tensor::cat(&frames, 2);
    let whole = tch::no_grad(|| vae.decode(&latents)).unwrap();
    assert_eq!(whole.size(), [1, 3, 1 + 4 * 23, 32, 48]);
    assert_eq!(rel_err(&streamed, &whole), 0.0);
}

#[test]
fn bad_inputs_are_clear_errors() {
    let (vae, store) = WanVae::random(&small(), Kind::Float, Device::Cpu, 6).unwrap();
    let err = |r: anyhow::Result<Tensor>| format!("{:#}", r.err().expect("should fail"));
    let e = err(vae.encode(&video(8, 32, 48, 0)));
    assert!(e.contains("8 frames") && e.contains("1+4k"), "{e}");
    let e = err(vae.encode(&video(5, 40, 48, 0)));
    assert!(e.contains("40x48") && e.contains("multiples of 16"), "{e}");
    let nan = video(5, 32, 48, 0);
    let _ = nan.narrow(2, 3, 1).fill_(f64::NAN);
    let e = err(vae.encode(&nan));
    assert!(e.contains("NaN"), "{e}");
    let e = err(vae.decode(&Tensor::zeros([1, 16, 2, 2, 3], (Kind::Float, Device::Cpu))));
    assert!(e.contains("[B, 48, T, h, w]"), "{e}");

    let dir = tmp_dir("vae-bad");
    let path = dir.join("vae.safetensors");
    Tensor::write_safetensors(&store.named_parameters(), &path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let e = format!("{:#}", WanVae::load(&path, &small(), Kind::Float, Device::Cpu).err().unwrap());
    assert!(e.contains("vae.safetensors") && e.contains("not a valid safetensors file"), "{e}");
    // A state dict of another width names the first mismatching key.
    let wide = dir.join("wide.safetensors");
    let (_, wide_store) = WanVae::random(&VaeConfig::with_width(16, 16), Kind::Float, Device::Cpu, 7).unwrap();
    Tensor::write_safetensors(&wide_store.named_parameters(), &wide).unwrap();
    let e = format!("{:#}", WanVae::load(&wide, &small(), Kind::Float, Device::Cpu).err().unwrap());
    assert!(e.contains("encoder.conv1.weight") && e.contains("expected [8, 12, 3, 3, 3]"), "{e}");
}

#[test]
fn a_vae_of_stride_8_doubles_the_latent_grid_and_keeps_its_properties() {
    let cfg = small().with_spatial_stride(8).unwrap();
    assert_eq!((cfg.spatial_stride(), small().spatial_stride()), (8, 16));
    assert_eq!(cfg.latent_shape(13, 32, 48), [48, 4, 4, 6]);
    let (vae, _) = WanVae::random(&cfg, Kind::Float, Device::Cpu, 8).unwrap();
    let long = video(13, 32, 48, 9);
    let full = tch::no_grad(|| vae.encode(&long)).unwrap();
    assert_eq!(full.size(), [1, 48, 4, 4, 6]);
    let prefix = tch::no_grad(|| vae.encode(&long.narrow(2, 0, 5))).unwrap();
    assert!(rel_err(&prefix, &full.narrow(2, 0, 2)) < 1e-6, "encoding is causal");

    let mut stream = vae.decoder_stream();
    let streamed: Vec<Tensor> = tch::no_grad(|| (0..4).map(|i| stream.next(&full.narrow(2, i, 1)).unwrap()).collect());
    let whole = tch::no_grad(|| vae.decode(&full)).unwrap();
    assert_eq!(whole.size(), [1, 3, 13, 32, 48]);
    assert_eq!(rel_err(&Tensor::cat(&streamed, 2), &whole), 0.0);

    let e = format!("{:#}", vae.encode(&video(5, 36, 48, 0)).err().expect("36 is not a multiple of 8"));
    assert!(e.contains("36x48") && e.contains("multiples of 8"), "{e}");
    let e = format!("{:#}", small().with_spatial_stride(4).err().unwrap());
    assert!(e.contains("8 or 16, got 4"), "{e}");
    let two_stages = VaeConfig { dim_mult: vec![1, 2], temporal_downsample: vec![true], ..small() };
    assert!(format!("{:#}", two_stages.validate().err().unwrap()).contains("3 or 4 stages"));
    // Widening in the last stage, which does not downsample, leaves its shortcut nothing to average.
    let widening = VaeConfig { dim_mult: vec![1, 2, 4], temporal_downsample: vec![true, true], ..small() };
    let e = format!("{:#}", widening.validate().err().unwrap());
    assert!(e.contains("stage 2 widens x2 without downsampling"), "{e}");
}

#[test]
fn a_round_trip_keeps_any_frame_count_and_equals_decode_of_encode() {
    let (vae, _) = WanVae::random(&small(), Kind::Float, Device::Cpu, 4).unwrap();
    let v = video(7, 32, 32, 5);
    let back = vae.round_trip(&v).unwrap();
    assert_eq!(back.size(), v.size());
    assert!(back.max().double_value(&[]) <= 1.0 && back.min().double_value(&[]) >= -1.0);
    // 7 frames are padded to 9 with the last frame; the first 7 decoded frames are kept.
    let padded = Tensor::cat(&[v.shallow_clone(), v.narrow(2, 6, 1).repeat([1, 1, 2, 1, 1])], 2);
    let direct = tch::no_grad(|| vae.decode(&vae.encode(&padded).unwrap())).unwrap().clamp(-1.0, 1.0);
    assert!(rel_err(&back, &direct.narrow(2, 0, 7)) < 1e-6);
    assert_eq!(vae.round_trip(&v.narrow(2, 0, 5)).unwrap().size(), [1, 3, 5, 32, 32]);
    let err = vae.round_trip(&v.narrow(1, 0, 2)).unwrap_err().to_string();
    assert!(err.contains("[B, 3, F, H, W]"), "{err}");
}
