//! The full Wan2.2-TI2V-5B module tree, built shape-only (no storage), checked against the key
//! list of `../shared/design/wan22-ti2v-5b-spec.md` section 5.1 (official `WanModel` names,
//! verified there by instantiating the reference on the meta device).

mod common;

use std::collections::BTreeMap;
use std::path::PathBuf;

use bwm_model::{BwmModel, ModelConfig, ParamStore};
use tch::Kind;

fn spec_path() -> PathBuf {
    let shared = bwm_testdir::shared();
    shared.join("design/wan22-ti2v-5b-spec.md")
}

fn parse_shape(s: &str) -> Vec<i64> {
    s.trim().trim_matches(|c| c == '[' || c == ']').split(',').map(|d| d.trim().parse().unwrap()).collect()
}

/// Rows `| `key` / `.bias` | [shape] / [shape] |` of section 5.1, blocks expanded over N.
fn spec_keys(num_layers: i64) -> BTreeMap<String, Vec<i64>> {
    let text = std::fs::read_to_string(spec_path()).unwrap();
    let start = text.find("### 5.1").expect("spec section 5.1");
    let end = text[start..].find("### 5.2").expect("spec section 5.2") + start;
    let mut keys = BTreeMap::new();
    for line in text[start..end].lines() {
        let cols: Vec<&str> = line.split('|').map(str::trim).collect();
        if cols.len() < 4 || !cols[1].starts_with('`') {
            continue;
        }
        let names: Vec<String> = cols[1].split(" / ").map(|n| n.trim_matches('`').to_string()).collect();
        let shapes: Vec<Vec<i64>> = cols[2].split(" / ").map(parse_shape).collect();
        assert_eq!(names.len(), shapes.len(), "spec row: {line}");
        let stem = names[0].rsplit_once('.').map(|(s, _)| s.to_string()).unwrap_or_default();
        for (name, shape) in names.iter().zip(shapes) {
            let full = if name.starts_with('.') { format!("{stem}{name}") } else { name.clone() };
            if full.contains(".N.") {
                for i in 0..num_layers {
                    keys.insert(full.replace(".N.", &format!(".{i}.")), shape.clone());
                }
            } else {
                keys.insert(full, shape);
            }
        }
    }
    keys
}

#[test]
fn wan22_ti2v_5b_tree_matches_the_spec_without_allocating() {
    let cfg = ModelConfig::preset("wan22_ti2v_5b").unwrap();
    let store = ParamStore::shapes_only(Kind::BFloat16);
    let model = BwmModel::build(&store, &cfg).unwrap();
    let params = store.named_parameters();

    let dit: Vec<_> = params.iter().filter(|(n, _)| !n.starts_with("action_encoder.")).collect();
    let dit_count: i64 = dit.iter().map(|(_, t)| t.size().iter().product::<i64>()).sum();
    println!("DiT: {} tensors, {dit_count} parameters", dit.len());
    assert_eq!(dit.len(), 825);
    assert_eq!(dit_count, 4_999_787_712);

    let ours: BTreeMap<String, Vec<i64>> = dit.iter().map(|(n, t)| (n.clone(), t.size())).collect();
    let spec = spec_keys(cfg.dit.num_layers);
    assert_eq!(spec.len(), 825, "spec table parse");
    assert_eq!(ours, spec);

    let action: i64 = params
        .iter()
        .filter(|(n, _)| n.starts_with("action_encoder."))
        .map(|(_, t)| t.size().iter().product::<i64>())
        .sum();
    // mlp1: 14*3072+3072 + 3072*3072+3072; mlp2: 56*12288+12288 + 12288*3072+3072
    assert_eq!(action, 9_486_336 + 38_452_224);
    assert_eq!(model.dit.blocks.len(), 30);
    // Expanded scalars: the whole tree holds one element per tensor.
    assert!(params.iter().all(|(_, t)| t.stride().iter().all(|&s| s == 0)));
}
