//! Reads the bundled episodes (`../shared/data/bwm-demo`, three RoboTwin episodes in the BWM layout).

use std::path::PathBuf;

use bwm_data::{ActionSpec, ActionStats, BwmDataset};

fn demo_root() -> PathBuf {
    let shared = bwm_testdir::shared();
    shared.join("data/bwm-demo")
}

#[test]
fn reads_the_bundled_episodes_with_aligned_actions() {
    let ds = BwmDataset::open(&demo_root()).unwrap();
    assert_eq!(ds.episodes.len(), 3);
    let spec = ActionSpec::eef_abs();
    let stats = ActionStats::read(&demo_root().join("stat.json"), &spec.stats_group).unwrap();
    assert_eq!(stats.dim(), 14);
    for ep in &ds.episodes {
        let actions = ds.actions(ep, &spec).unwrap();
        assert_eq!(actions.len(), ep.length, "frame count equals parquet rows");
        assert!(actions.iter().all(|a| a.len() == 14));
        let n = stats.normalize(&actions[0]);
        assert!(n.iter().all(|v| (-1.0..=1.0).contains(v)));
    }
    // Episode 40, frame 0: left gripper (state index 6) open = 1.0, right xyz = state[20..23].
    let first = &ds.actions(&ds.episodes[0], &spec).unwrap()[0];
    assert_eq!(first[6], 1.0);
    assert!((first[7] - 0.306_433_08).abs() < 1e-6);
}

#[test]
fn unknown_column_is_a_clear_error() {
    let ds = BwmDataset::open(&demo_root()).unwrap();
    let spec = ActionSpec { column: "nope".into(), ..ActionSpec::eef_abs() };
    let e = ds.actions(&ds.episodes[0], &spec).unwrap_err().to_string();
    assert!(e.contains("no column 'nope'") && e.contains("observation.state"), "{e}");
}
