//! Weight files written by the tests themselves: round trips, layouts, shards, and every kind of
//! bad file or bad input giving a clear error.

mod common;

use std::path::Path;

use bwm_model::{frame_timesteps, BwmModel, Layout, ModelConfig};
use common::{rel_err, tmp_dir, torch_rng};
use tch::{Device, Kind, Tensor};

fn tiny() -> ModelConfig {
    ModelConfig::preset("tiny").unwrap()
}

fn save(params: &[(String, Tensor)], path: &Path) {
    Tensor::write_safetensors(params, path).unwrap();
}

/// Latents for 1+8+8 pixel frames (5 latent frames) of a 64x96 video and their actions.
fn inputs(seed: i64) -> (Tensor, Tensor, Tensor) {
    let (latents, actions) = bwm_model::vb::with_seed(seed, || {
        (Tensor::randn([2, 48, 5, 4, 6], (Kind::Float, Device::Cpu)), Tensor::rand([2, 17, 14], (Kind::Float, Device::Cpu)) * 2.0 - 1.0)
    });
    let t = frame_timesteps(&Tensor::from_slice(&[875.0f32, 312.5]), 5, 3);
    (latents, t, actions)
}

fn forward(m: &BwmModel) -> Tensor {
    let (x, t, a) = inputs(1);
    tch::no_grad(|| m.forward(&x, &t, &a)).unwrap()
}

fn load_err(path: &Path, layout: Layout) -> String {
    match BwmModel::load(path, layout, &tiny(), Kind::Float, Device::Cpu) {
        Ok(_) => panic!("loading {} should fail", path.display()),
        Err(e) => format!("{e:#}"),
    }
}

#[test]
fn round_trip_layouts_and_shards() {
    let _rng = torch_rng();
    let dir = tmp_dir("model-io");
    let m = BwmModel::random(&tiny(), Kind::Float, Device::Cpu, 3).unwrap();
    let params = m.store.named_parameters();
    let reference = forward(&m);

    let single = dir.join("model.safetensors");
    save(&params, &single);
    let loaded = BwmModel::load(&single, Layout::WanNative, &tiny(), Kind::Float, Device::Cpu).unwrap();
    assert_eq!(rel_err(&forward(&loaded), &reference), 0.0);

    // BWM release layout: no text_embedding, action encoder under `pipe.action_encoder.`.
    let release: Vec<(String, Tensor)> = params
        .iter()
        .filter(|(n, _)| !n.starts_with("text_embedding."))
        .map(|(n, t)| {
            let n = if n.starts_with("action_encoder.") { format!("pipe.{n}") } else { n.clone() };
            (n, t.shallow_clone())
        })
        .collect();
    let release_path = dir.join("step-12000.safetensors");
    save(&release, &release_path);
    let loaded = BwmModel::load(&release_path, Layout::BwmRelease, &tiny(), Kind::Float, Device::Cpu).unwrap();
    assert!(loaded.dit.text_embedding.is_none());
    assert_eq!(rel_err(&forward(&loaded), &reference), 0.0);

    // Two shards and an index, in bf16 on disk, cast to f32 on load.
    let shard_dir = dir.join("sharded");
    std::fs::create_dir_all(&shard_dir).unwrap();
    let (a, b) = params.split_at(params.len() / 2);
    let bf16 = |p: &[(String, Tensor)]| p.iter().map(|(n, t)| (n.clone(), t.to_kind(Kind::BFloat16))).collect::<Vec<_>>();
    save(&bf16(a), &shard_dir.join("model-00001-of-00002.safetensors"));
    save(&bf16(b), &shard_dir.join("model-00002-of-00002.safetensors"));
    let map: serde_json::Map<String, serde_json::Value> = a
        .iter()
        .map(|(n, _)| (n.clone(), "model-00001-of-00002.safetensors".into()))
        .chain(b.iter().map(|(n, _)| (n.clone(), "model-00002-of-00002.safetensors".into())))
        .collect();
    std::fs::write(
        shard_dir.join("model.safetensors.index.json"),
        serde_json::to_string(&serde_json::json!({"metadata": {}, "weight_map": map})).unwrap(),
    )
    .unwrap();
    let loaded = BwmModel::load(&shard_dir, Layout::WanNative, &tiny(), Kind::Float, Device::Cpu).unwrap();
    assert_eq!(loaded.dit.blocks[0].self_attn.q.weight.kind(), Kind::Float);
    let e = rel_err(&forward(&loaded), &reference);
    assert!(e < 2e-2, "bf16-stored weights: rel err {e}");
}

#[test]
fn bad_weight_files_name_the_file_and_the_key() {
    let _rng = torch_rng();
    let dir = tmp_dir("bad-weights");
    let m = BwmModel::random(&tiny(), Kind::Float, Device::Cpu, 4).unwrap();
    let params = m.store.named_parameters();
    let one_line = |e: &str| assert!(!e.contains('\n'), "error spans lines: {e}");

    let missing = dir.join("missing.safetensors");
    save(&params.iter().filter(|(n, _)| n != "blocks.1.ffn.0.weight").map(|(n, t)| (n.clone(), t.shallow_clone())).collect::<Vec<_>>(), &missing);
    let e = load_err(&missing, Layout::WanNative);
    assert!(e.contains("missing.safetensors") && e.contains("missing key 'blocks.1.ffn.0.weight'"), "{e}");
    one_line(&e);

    let extra = dir.join("extra.safetensors");
    let mut with_extra: Vec<(String, Tensor)> = params.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
    with_extra.push(("blocks.0.lora_a.weight".into(), Tensor::zeros([2, 2], (Kind::Float, Device::Cpu))));
    save(&with_extra, &extra);
    let e = load_err(&extra, Layout::WanNative);
    assert!(e.contains("extra.safetensors") && e.contains("unexpected key 'blocks.0.lora_a.weight'"), "{e}");
    one_line(&e);

    let shape = dir.join("shape.safetensors");
    let reshaped: Vec<(String, Tensor)> = params
        .iter()
        .map(|(n, t)| (n.clone(), if n == "head.head.weight" { Tensor::zeros([10, 96], (Kind::Float, Device::Cpu)) } else { t.shallow_clone() }))
        .collect();
    save(&reshaped, &shape);
    let e = load_err(&shape, Layout::WanNative);
    assert!(e.contains("shape.safetensors") && e.contains("'head.head.weight' has shape [10, 96], expected [192, 96]"), "{e}");
    one_line(&e);

    let truncated = dir.join("truncated.safetensors");
    save(&params, &truncated);
    let bytes = std::fs::read(&truncated).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len() - 1000]).unwrap();
    let e = load_err(&truncated, Layout::WanNative);
    assert!(e.contains("truncated.safetensors") && e.contains("not a valid safetensors file"), "{e}");
    one_line(&e);

    let e = load_err(&dir.join("absent.safetensors"), Layout::WanNative);
    assert!(e.contains("absent.safetensors"), "{e}");
}

#[test]
fn bad_inputs_say_what_was_expected() {
    let _rng = torch_rng();
    let m = BwmModel::random(&tiny(), Kind::Float, Device::Cpu, 5).unwrap();
    let (x, t, a) = inputs(2);
    let err = |r: anyhow::Result<Tensor>| format!("{:#}", r.err().expect("should fail"));

    let e = err(m.forward(&x, &t, &a.narrow(1, 0, 16)));
    assert!(e.contains("16 frames") && e.contains("4k+1"), "{e}");

    let e = err(m.forward(&x.narrow(2, 0, 4), &t.narrow(1, 0, 4), &a));
    assert!(e.contains("cover 5 latent frames") && e.contains("latents have 4"), "{e}");

    let e = err(m.forward(&x.narrow(1, 0, 16), &t, &a));
    assert!(e.contains("16 channels") && e.contains("in_dim = 48"), "{e}");

    let e = err(m.forward(&x.narrow(3, 0, 3), &t, &a));
    assert!(e.contains("multiple of the patch size"), "{e}");

    let e = err(m.forward(&x, &t.narrow(1, 0, 2), &a));
    assert!(e.contains("timesteps must be [B, F] = [2, 5]"), "{e}");

    let e = err(m.forward(&x, &t, &a.narrow(2, 0, 7)));
    assert!(e.contains("actions must be [B, F, 14]"), "{e}");
}

#[test]
fn bf16_forward_stays_close_to_f32() {
    let _rng = torch_rng();
    let cfg = tiny();
    let f32_model = BwmModel::random(&cfg, Kind::Float, Device::Cpu, 11).unwrap();
    let bf16_model = BwmModel::random(&cfg, Kind::BFloat16, Device::Cpu, 11).unwrap();
    assert_eq!(bf16_model.dit.blocks[0].ffn.l0.weight.kind(), Kind::BFloat16);
    let out32 = forward(&f32_model);
    let out16 = forward(&bf16_model);
    assert_eq!(out16.kind(), Kind::Float, "predictions come out in fp32");
    let e = rel_err(&out16, &out32);
    println!("bf16 vs f32 rel err {e:.3e}");
    assert!(e < 2e-2, "bf16 rel err {e}");
    assert!(e > 0.0, "bf16 path must actually run in bf16");
}

#[test]
fn a_bf16_residual_stream_stays_close_to_the_fp32_one() {
    let _rng = torch_rng();
    let cfg = tiny();
    let mut m = BwmModel::random(&cfg, Kind::BFloat16, Device::Cpu, 11).unwrap();
    let reference = forward(&m);
    m.dit.residual = Kind::BFloat16;
    let (x, t, a) = inputs(1);
    let mut stream = Vec::new();
    let out = tch::no_grad(|| m.forward_traced(&x, &t, &a, &mut |name, v| stream.push((name.to_string(), v.kind())))).unwrap();
    for (name, kind) in &stream {
        if name == "tokens_in" || name.ends_with("_out") {
            assert_eq!(*kind, Kind::BFloat16, "{name} should be in the residual dtype");
        }
    }
    assert!(stream.iter().any(|(n, _)| n == "block1_out"), "the trace saw the blocks");
    assert_eq!(out.kind(), Kind::Float, "predictions come out in fp32");
    let e = rel_err(&out, &reference);
    println!("bf16 residual vs fp32 residual rel err {e:.3e}");
    assert!(e > 0.0 && e < 2e-2, "bf16 residual rel err {e}");
}
