//! The shipped run configs parse, validate, and say what the issue's recipe says.

use std::path::PathBuf;

use bwm_trainer::RunConfig;

fn load(name: &str) -> RunConfig {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs").join(name);
    RunConfig::load(&path, &[]).unwrap_or_else(|e| panic!("{name}: {e:#}"))
}

#[test]
fn paper_recipe() {
    let c = load("bwm-wan22-ti2v-5b.toml");
    let m = c.model.model_config().unwrap();
    assert_eq!((m.dit.dim, m.dit.num_layers, m.action.action_dim, m.action.prepend, m.action.group), (3072, 30, 14, 3, 4));
    assert_eq!((c.train.micro_batch, c.train.grad_accum, c.train.steps), (1, 4, 12000));
    assert!(c.train.recompute);
    assert_eq!(c.model.dtype, bwm_trainer::config::Dtype::Bf16);
    assert_eq!(c.objective.condition_latents, 3);
    assert_eq!(c.optim.lr, 1e-5);
}

#[test]
fn public_checkpoint_and_tiny_configs() {
    let p = load("bwm-public-ckpt.toml");
    assert!(matches!(p.model.init, bwm_trainer::config::InitSource::BwmCheckpoint { .. }));
    let t = load("tiny.toml");
    assert_eq!(t.model.preset, "tiny");
    assert!(t.validation.vae.is_some());
    assert_eq!(t.validation.solver, bwm_model::schedule::Solver::Euler);
}

#[test]
fn the_validation_solver_is_named_as_on_the_command_line() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/tiny.toml");
    let c = RunConfig::load(&path, &["validation.solver=dpm++2m".to_string()]).unwrap();
    assert_eq!(c.validation.solver, bwm_model::schedule::Solver::DpmPp2M);
    let err = format!("{:#}", RunConfig::load(&path, &["validation.solver=unipc".to_string()]).unwrap_err());
    assert!(err.contains("unipc") && err.contains("dpm++2m"), "{err}");
}

#[test]
fn the_readme_lora_override_of_the_5b_recipe() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/bwm-wan22-ti2v-5b.toml");
    let overrides = [
        r#"model.lora={rank=64, targets=["blocks.*.self_attn.*", "blocks.*.cross_attn.*", "blocks.*.ffn.*"]}"#.to_string(),
        r#"train.trainable=["*.lora_A.weight", "*.lora_B.weight", "action_encoder.*"]"#.to_string(),
    ];
    let c = RunConfig::load(&path, &overrides).unwrap();
    let lora = c.model.lora.clone().unwrap();
    assert_eq!((lora.rank, lora.scale()), (64, 1.0));
    // The module tree without storage: every attention and FFN linear of the 30 blocks carries
    // an adapter (8 of 3072 x 3072, 2 between 3072 and 14336).
    let store = bwm_model::ParamStore::shapes_only(tch::Kind::BFloat16);
    bwm_model::BwmModel::build_converted(&store, &c.model.model_config().unwrap(), |m| bwm_model::lora::add_adapters(m, lora, 0).map(drop)).unwrap();
    let named = store.named_parameters();
    let adapters: Vec<_> = named.iter().filter(|(n, _)| bwm_model::lora::is_adapter_key(n)).collect();
    assert_eq!(adapters.len(), 30 * 10 * 2);
    let adapter_params: i64 = adapters.iter().map(|(_, t)| t.size().iter().product::<i64>()).sum();
    assert_eq!(adapter_params, 30 * (8 * 64 * (3072 + 3072) + 2 * 64 * (3072 + 14336)));
    let trained = bwm_trainer::optim::select_trainable(&named, &c.trainable_patterns(), &c.train.frozen).unwrap();
    assert_eq!(trained.len(), adapters.len() + named.iter().filter(|(n, _)| n.starts_with("action_encoder.")).count());
}
