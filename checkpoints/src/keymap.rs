//! DiT key maps between the three layouts people publish the Wan2.2-TI2V DiT (+ BWM action
//! encoder) in:
//!
//! - **Wan-native** (`wan`): the official `WanModel` names (`blocks.N.self_attn.q.weight`,
//!   `head.modulation`, ...), also DiffSynth-Studio's, and this project's canonical names; the BWM
//!   action encoder under `action_encoder.`.
//! - **diffusers** (`diffusers`): `WanTransformer3DModel` names (docs/wan22-ti2v-5b.md, section
//!   "DiT"; the converter's `TRANSFORMER_KEYS_RENAME_DICT`); the action encoder keeps its BWM names under
//!   `action_encoder.` (diffusers has no such module; an export stores it as its own component).
//! - **BWM release** (`bwm-release`): Wan-native DiT names, the action encoder under
//!   `pipe.action_encoder.` (DiffSynth's `export_trainable_state_dict` of the pipeline), and no
//!   `text_embedding` (frozen and unused when actions replace text).
//!
//! The maps work on whole dot-separated segments (not substring replacement), so the
//! `norm3 -> norm2` swap of the cross-attention LayerNorm cannot cascade, `head.modulation` and
//! `blocks.N.modulation` cannot be confused, and each map is a bijection on the model's key set
//! (tested on the full 5B tree).
//!
//! **Tensors**: no layout splits, fuses or reshapes a tensor. Checked against diffusers 0.42.1
//! (`WanTransformer3DModel`): `scale_shift_table` is [1, 2, D] like `head.modulation`,
//! `blocks.N.scale_shift_table` is [1, 6, D] like `blocks.N.modulation` (both added to the time
//! projection and chunked in the same order), `condition_embedder.time_proj` is Linear(D, 6D) with
//! the same row order as `time_projection.1` (`unflatten(2, (6, -1))` on both sides), q/k/v/o stay
//! separate Linears (no fused `to_qkv`), the RMSNorms over the full width (`rms_norm_across_heads`)
//! keep their `[D]` weights. [`transform_tensor`] is therefore the identity; it exists so that a
//! future layout with a real transform has one place to put it.

use std::fmt;
use std::str::FromStr;

use anyhow::{bail, Result};
use tch::Tensor;

/// A DiT checkpoint layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DitLayout {
    WanNative,
    Diffusers,
    BwmRelease,
}

impl DitLayout {
    pub const ALL: [DitLayout; 3] = [DitLayout::WanNative, DitLayout::Diffusers, DitLayout::BwmRelease];

    /// The name used on the command line and in `config.json`.
    pub fn name(self) -> &'static str {
        match self {
            DitLayout::WanNative => "wan",
            DitLayout::Diffusers => "diffusers",
            DitLayout::BwmRelease => "bwm-release",
        }
    }

    /// The prefix of the action encoder's keys in this layout.
    pub fn action_prefix(self) -> &'static str {
        match self {
            DitLayout::BwmRelease => "pipe.action_encoder.",
            _ => "action_encoder.",
        }
    }
}

impl fmt::Display for DitLayout {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for DitLayout {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "wan" | "wan-native" | "native" => DitLayout::WanNative,
            "diffusers" => DitLayout::Diffusers,
            "bwm-release" | "bwm" | "release" => DitLayout::BwmRelease,
            other => bail!("unknown layout '{other}' (allowed: wan, diffusers, bwm-release)"),
        })
    }
}

/// The Wan-native prefix of the action encoder (the project's canonical names).
pub const ACTION_PREFIX: &str = "action_encoder.";

/// Prefix of the module that actions make unused (absent from training checkpoints and the BWM
/// release by design).
pub const TEXT_EMBEDDING_PREFIX: &str = "text_embedding.";

fn is_index(s: &str) -> bool {
    !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit())
}

/// Diffusers name of a Wan-native DiT key (action-encoder keys unchanged); `None` when the key is
/// not one of the Wan2.2-TI2V DiT / BWM action encoder.
fn wan_to_diffusers(key: &str) -> Option<String> {
    if key.starts_with(ACTION_PREFIX) {
        return Some(key.to_string());
    }
    let p: Vec<&str> = key.split('.').collect();
    let tail = |from: usize| p[from..].join(".");
    Some(match p.as_slice() {
        ["patch_embedding", _] => key.to_string(),
        ["text_embedding", "0", _] => format!("condition_embedder.text_embedder.linear_1.{}", tail(2)),
        ["text_embedding", "2", _] => format!("condition_embedder.text_embedder.linear_2.{}", tail(2)),
        ["time_embedding", "0", _] => format!("condition_embedder.time_embedder.linear_1.{}", tail(2)),
        ["time_embedding", "2", _] => format!("condition_embedder.time_embedder.linear_2.{}", tail(2)),
        ["time_projection", "1", _] => format!("condition_embedder.time_proj.{}", tail(2)),
        ["head", "modulation"] => "scale_shift_table".to_string(),
        ["head", "head", _] => format!("proj_out.{}", tail(2)),
        ["blocks", n, rest @ ..] if is_index(n) => {
            let inner = match rest {
                ["modulation"] => "scale_shift_table".to_string(),
                [attn @ ("self_attn" | "cross_attn"), proj, _] => {
                    let a = if *attn == "self_attn" { "attn1" } else { "attn2" };
                    match *proj {
                        "q" | "k" | "v" => format!("{a}.to_{proj}.{}", tail(4)),
                        "o" => format!("{a}.to_out.0.{}", tail(4)),
                        "norm_q" | "norm_k" => format!("{a}.{proj}.{}", tail(4)),
                        _ => return None,
                    }
                }
                ["norm3", _] => format!("norm2.{}", tail(3)),
                ["ffn", "0", _] => format!("ffn.net.0.proj.{}", tail(4)),
                ["ffn", "2", _] => format!("ffn.net.2.{}", tail(4)),
                _ => return None,
            };
            format!("blocks.{n}.{inner}")
        }
        _ => return None,
    })
}

/// Wan-native name of a diffusers `WanTransformer3DModel` key (action-encoder keys unchanged).
fn diffusers_to_wan(key: &str) -> Option<String> {
    if key.starts_with(ACTION_PREFIX) {
        return Some(key.to_string());
    }
    let p: Vec<&str> = key.split('.').collect();
    let tail = |from: usize| p[from..].join(".");
    Some(match p.as_slice() {
        ["patch_embedding", _] => key.to_string(),
        ["condition_embedder", "text_embedder", "linear_1", _] => format!("text_embedding.0.{}", tail(3)),
        ["condition_embedder", "text_embedder", "linear_2", _] => format!("text_embedding.2.{}", tail(3)),
        ["condition_embedder", "time_embedder", "linear_1", _] => format!("time_embedding.0.{}", tail(3)),
        ["condition_embedder", "time_embedder", "linear_2", _] => format!("time_embedding.2.{}", tail(3)),
        ["condition_embedder", "time_proj", _] => format!("time_projection.1.{}", tail(2)),
        ["scale_shift_table"] => "head.modulation".to_string(),
        ["proj_out", _] => format!("head.head.{}", tail(1)),
        ["blocks", n, rest @ ..] if is_index(n) => {
            let inner = match rest {
                ["scale_shift_table"] => "modulation".to_string(),
                [attn @ ("attn1" | "attn2"), rest @ ..] => {
                    let a = if *attn == "attn1" { "self_attn" } else { "cross_attn" };
                    match rest {
                        [proj @ ("to_q" | "to_k" | "to_v"), _] => format!("{a}.{}.{}", &proj[3..], tail(4)),
                        ["to_out", "0", _] => format!("{a}.o.{}", tail(5)),
                        [norm @ ("norm_q" | "norm_k"), _] => format!("{a}.{norm}.{}", tail(4)),
                        _ => return None,
                    }
                }
                ["norm2", _] => format!("norm3.{}", tail(3)),
                ["ffn", "net", "0", "proj", _] => format!("ffn.0.{}", tail(6)),
                ["ffn", "net", "2", _] => format!("ffn.2.{}", tail(5)),
                _ => return None,
            };
            format!("blocks.{n}.{inner}")
        }
        _ => return None,
    })
}

/// Whether `key` is a Wan-native key of the Wan2.2-TI2V DiT / BWM action encoder family (any
/// width or depth).
pub fn is_wan_key(key: &str) -> bool {
    wan_to_diffusers(key).is_some()
}

/// The name of Wan-native `key` in `layout`, or an error naming the key when it belongs to no
/// module of the Wan2.2-TI2V DiT / BWM action encoder.
pub fn to_layout(layout: DitLayout, key: &str) -> Result<String> {
    let mapped = match layout {
        DitLayout::WanNative => is_wan_key(key).then(|| key.to_string()),
        DitLayout::Diffusers => wan_to_diffusers(key),
        DitLayout::BwmRelease => is_wan_key(key).then(|| match key.strip_prefix(ACTION_PREFIX) {
            Some(rest) => format!("pipe.{ACTION_PREFIX}{rest}"),
            None => key.to_string(),
        }),
    };
    match mapped {
        Some(k) => Ok(k),
        None => bail!("'{key}' is not a key of the Wan2.2-TI2V DiT or the BWM action encoder (Wan-native names expected)"),
    }
}

/// The Wan-native name of `key` given in `layout`, or an error naming the key.
pub fn from_layout(layout: DitLayout, key: &str) -> Result<String> {
    let mapped = match layout {
        DitLayout::WanNative => is_wan_key(key).then(|| key.to_string()),
        DitLayout::Diffusers => diffusers_to_wan(key),
        DitLayout::BwmRelease => {
            let wan = match key.strip_prefix("pipe.") {
                Some(rest) if rest.starts_with(ACTION_PREFIX) => rest.to_string(),
                _ if key.starts_with(ACTION_PREFIX) => String::new(),
                _ => key.to_string(),
            };
            is_wan_key(&wan).then_some(wan)
        }
    };
    match mapped {
        Some(k) => Ok(k),
        None => bail!("'{key}' is not a {layout}-layout key of the Wan2.2-TI2V DiT or the BWM action encoder"),
    }
}

/// Converts a tensor stored under Wan-native `key` for `layout`. The identity for every layout
/// (see the module docs: no layout splits or fuses tensors).
pub fn transform_tensor(_layout: DitLayout, _key: &str, tensor: Tensor) -> Tensor {
    tensor
}

/// What a set of keys says about its layout.
#[derive(Debug, Default, Clone, Copy)]
struct Votes {
    wan: usize,
    diffusers: usize,
    release: usize,
    action_plain: usize,
}

/// The layout of a DiT key set, judged from keys only one layout uses: `pipe.action_encoder.`
/// (BWM release), diffusers-only module names, Wan-only module names. An error when the keys mix
/// layouts or belong to no known layout.
pub fn detect_layout(keys: &[String]) -> Result<DitLayout> {
    let mut v = Votes::default();
    for k in keys {
        if k.starts_with("pipe.action_encoder.") {
            v.release += 1;
        } else if k.starts_with(ACTION_PREFIX) {
            v.action_plain += 1;
        } else if diffusers_to_wan(k).is_some() && !k.starts_with("patch_embedding.") {
            v.diffusers += 1;
        } else if is_wan_key(k) && !k.starts_with("patch_embedding.") {
            v.wan += 1;
        }
    }
    let example = |pred: &dyn Fn(&str) -> bool| keys.iter().find(|k| pred(k)).cloned().unwrap_or_default();
    if v.wan > 0 && v.diffusers > 0 {
        bail!(
            "the keys mix the Wan-native and diffusers layouts (e.g. '{}' and '{}'); convert one part first",
            example(&|k| is_wan_key(k) && !k.starts_with(ACTION_PREFIX) && !k.starts_with("patch_embedding.")),
            example(&|k| diffusers_to_wan(k).is_some() && !k.starts_with(ACTION_PREFIX) && !k.starts_with("patch_embedding."))
        );
    }
    if v.release > 0 && v.action_plain > 0 {
        bail!(
            "the keys hold the action encoder twice, under 'pipe.action_encoder.' and under 'action_encoder.' (e.g. '{}')",
            example(&|k| k.starts_with(ACTION_PREFIX))
        );
    }
    if v.release > 0 {
        if v.diffusers > 0 {
            bail!("the keys mix the BWM-release action prefix 'pipe.action_encoder.' with diffusers DiT names");
        }
        return Ok(DitLayout::BwmRelease);
    }
    if v.diffusers > 0 {
        return Ok(DitLayout::Diffusers);
    }
    if v.wan > 0 || v.action_plain > 0 {
        return Ok(DitLayout::WanNative);
    }
    match keys.first() {
        Some(k) => bail!("no key names a Wan2.2-TI2V DiT module in any known layout (first key: '{k}')"),
        None => bail!("no tensors"),
    }
}

/// Wan-native names for every key of `keys` given in `layout`: (file key, Wan-native key), with an
/// error for an unknown key or two file keys that map to the same Wan-native name.
pub fn map_keys_from(layout: DitLayout, keys: &[String]) -> Result<Vec<(String, String)>> {
    let mut seen: std::collections::BTreeMap<String, String> = std::collections::BTreeMap::new();
    let mut out = Vec::with_capacity(keys.len());
    for k in keys {
        let wan = from_layout(layout, k)?;
        if let Some(prev) = seen.insert(wan.clone(), k.clone()) {
            bail!("name collision: '{prev}' and '{k}' both map to the Wan-native key '{wan}'");
        }
        out.push((k.clone(), wan));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_table_rows() {
        let rows = [
            ("patch_embedding.weight", "patch_embedding.weight"),
            ("text_embedding.0.weight", "condition_embedder.text_embedder.linear_1.weight"),
            ("text_embedding.2.bias", "condition_embedder.text_embedder.linear_2.bias"),
            ("time_embedding.0.weight", "condition_embedder.time_embedder.linear_1.weight"),
            ("time_embedding.2.bias", "condition_embedder.time_embedder.linear_2.bias"),
            ("time_projection.1.weight", "condition_embedder.time_proj.weight"),
            ("head.modulation", "scale_shift_table"),
            ("head.head.weight", "proj_out.weight"),
            ("blocks.7.modulation", "blocks.7.scale_shift_table"),
            ("blocks.0.self_attn.q.weight", "blocks.0.attn1.to_q.weight"),
            ("blocks.0.self_attn.o.bias", "blocks.0.attn1.to_out.0.bias"),
            ("blocks.0.self_attn.norm_k.weight", "blocks.0.attn1.norm_k.weight"),
            ("blocks.29.cross_attn.v.weight", "blocks.29.attn2.to_v.weight"),
            ("blocks.29.cross_attn.o.weight", "blocks.29.attn2.to_out.0.weight"),
            ("blocks.3.norm3.weight", "blocks.3.norm2.weight"),
            ("blocks.3.ffn.0.weight", "blocks.3.ffn.net.0.proj.weight"),
            ("blocks.3.ffn.2.bias", "blocks.3.ffn.net.2.bias"),
            ("action_encoder.action_mlp1.0.weight", "action_encoder.action_mlp1.0.weight"),
        ];
        for (wan, diff) in rows {
            assert_eq!(to_layout(DitLayout::Diffusers, wan).unwrap(), diff, "{wan}");
            assert_eq!(from_layout(DitLayout::Diffusers, diff).unwrap(), wan, "{diff}");
        }
        assert_eq!(to_layout(DitLayout::BwmRelease, "action_encoder.action_mlp2.2.bias").unwrap(), "pipe.action_encoder.action_mlp2.2.bias");
        assert_eq!(from_layout(DitLayout::BwmRelease, "pipe.action_encoder.action_mlp2.2.bias").unwrap(), "action_encoder.action_mlp2.2.bias");
    }

    #[test]
    fn unknown_and_wrong_layout_keys_are_errors() {
        for (layout, key) in [
            (DitLayout::WanNative, "img_emb.proj.0.weight"),
            (DitLayout::WanNative, "blocks.0.norm2.weight"),
            (DitLayout::Diffusers, "blocks.0.norm3.weight"),
            (DitLayout::Diffusers, "blocks.0.self_attn.q.weight"),
            (DitLayout::BwmRelease, "action_encoder.action_mlp1.0.weight"),
            (DitLayout::WanNative, "blocks.x.modulation"),
        ] {
            assert!(from_layout(layout, key).is_err(), "{layout} {key}");
        }
    }

    #[test]
    fn detection_and_collisions() {
        let k = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        assert_eq!(detect_layout(&k(&["blocks.0.self_attn.q.weight", "action_encoder.action_mlp1.0.bias"])).unwrap(), DitLayout::WanNative);
        assert_eq!(detect_layout(&k(&["blocks.0.attn1.to_q.weight"])).unwrap(), DitLayout::Diffusers);
        assert_eq!(detect_layout(&k(&["head.modulation", "pipe.action_encoder.action_mlp1.0.bias"])).unwrap(), DitLayout::BwmRelease);
        let mixed = detect_layout(&k(&["head.modulation", "scale_shift_table"])).unwrap_err().to_string();
        assert!(mixed.contains("mix"), "{mixed}");
        let twice = detect_layout(&k(&["pipe.action_encoder.a.0.bias", "action_encoder.a.0.bias"])).unwrap_err().to_string();
        assert!(twice.contains("twice"), "{twice}");
        assert!(detect_layout(&k(&["foo"])).is_err());
        let e = map_keys_from(DitLayout::Diffusers, &k(&["blocks.0.attn2.norm_q.weight", "blocks.0.attn2.norm_q.weight"])).unwrap_err();
        assert!(e.to_string().contains("collision"), "{e}");
    }
}
