//! `bwm stats`: statistics against numpy, the stat.json round trip, the split, and the bundled
//! stat.json compared with statistics of the three bundled episodes.

mod common;

use bwm_data::stats::percentile;
use bwm_data::{write_stat_json, ActionStats};
use common::{run_python, tmp_dir};

/// Deterministic test values: a spread, repeats (ties), negatives and a constant column.
fn sample(n: usize, d: usize, seed: u64) -> Vec<Vec<f32>> {
    let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut next = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..n)
        .map(|i| {
            (0..d)
                .map(|j| match j {
                    0 => (next() * 20.0 - 10.0) as f32,
                    1 => (next() * 4.0).floor() as f32 * 0.5,
                    2 => 3.25,
                    _ => ((i * j) as f64).sin() as f32 * 1e-3 + (j as f32),
                })
                .collect()
        })
        .collect()
}

#[test]
fn statistics_match_numpy() {
    let Some(py) = bwm_testdir::python_with(bwm_testdir::Dep::Python, &["numpy"]) else { return };
    let dir = tmp_dir("stats-numpy");
    for (n, d) in [(1, 4), (2, 3), (5, 4), (7, 4), (100, 5), (1001, 4)] {
        let rows = sample(n, d, n as u64);
        let path = dir.join(format!("x{n}.f32"));
        let bytes: Vec<u8> = rows.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(&path, bytes).unwrap();
        let out = run_python(
            &py,
            r#"
import json, sys
import numpy as np
x = np.fromfile(sys.argv[1], dtype="<f4").reshape(int(sys.argv[2]), int(sys.argv[3])).astype(np.float64)
p = np.percentile(x, [1, 99], axis=0)
print(json.dumps({"min": x.min(0).tolist(), "max": x.max(0).tolist(), "p01": p[0].tolist(), "p99": p[1].tolist(),
                  "mean": x.mean(0).tolist(), "std": x.std(0).tolist()}))
"#,
            &[path.to_str().unwrap(), &n.to_string(), &d.to_string()],
        );
        let want: serde_json::Value = serde_json::from_str(&out).unwrap();
        let got = ActionStats::compute(rows.iter().map(Vec::as_slice)).unwrap();
        assert_eq!(got.shape, [d]);
        for (field, values, tol) in [
            ("min", &got.min, 0.0),
            ("max", &got.max, 0.0),
            ("p01", &got.p01, 1e-13),
            ("p99", &got.p99, 1e-13),
            ("mean", &got.mean, 1e-12),
            ("std", &got.std, 1e-12),
        ] {
            let want: Vec<f64> = serde_json::from_value(want[field].clone()).unwrap();
            for (i, (g, w)) in values.iter().zip(&want).enumerate() {
                assert!((g - w).abs() <= tol * w.abs().max(1.0), "n={n} {field}[{i}]: {g} vs numpy {w}");
            }
        }
    }
    // Single percentiles straight from numpy's definition, at awkward positions.
    let sorted = [-3.0, -1.0, 0.5, 0.5, 2.0, 7.0, 11.0];
    let out = run_python(
        &py,
        "import json, numpy as np; print(json.dumps([float(np.percentile([-3.0, -1.0, 0.5, 0.5, 2.0, 7.0, 11.0], q)) for q in [0, 1, 12.5, 50, 66.6, 99, 100]]))",
        &[],
    );
    let want: Vec<f64> = serde_json::from_str(&out).unwrap();
    for (q, w) in [0.0, 1.0, 12.5, 50.0, 66.6, 99.0, 100.0].iter().zip(want) {
        assert_eq!(percentile(&sorted, *q), w, "q = {q}");
    }
}

#[test]
fn stat_json_round_trips_and_bad_input_is_refused() {
    let dir = tmp_dir("stat-json");
    let a = ActionStats::compute(sample(50, 3, 1).iter().map(Vec::as_slice)).unwrap();
    let b = ActionStats::compute(sample(20, 2, 2).iter().map(Vec::as_slice)).unwrap();
    let path = dir.join("stat.json");
    write_stat_json(&path, &[("state_pose".into(), a.clone()), ("action_pose".into(), b.clone())]).unwrap();
    assert_eq!(ActionStats::read(&path, "state_pose").unwrap(), a);
    assert_eq!(ActionStats::read(&path, "action_pose").unwrap(), b);
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.find("state_pose").unwrap() < text.find("action_pose").unwrap(), "groups keep their order");
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1, "no temporary file left");

    assert!(ActionStats::compute(std::iter::empty::<&[f32]>()).is_err());
    assert!(ActionStats::compute([&[1.0f32, 2.0][..], &[1.0][..]]).is_err());
    assert!(ActionStats::compute([&[f32::NAN][..]]).is_err());
}

/// The bundled episodes' statistics read their videos (the frame counts): with the `video`
/// feature only (without it, reading a video is an error saying so: tests/without_features.rs).
#[cfg(feature = "video")]
mod bundled {
    use super::common::{demo_root, tmp_dir};
    use bwm_data::{compute_stats, open_dataset, split_episodes, write_stat_json, ActionSpec, ActionStats, SplitSpec, ValidationSize};

    /// The BWM release's groups: (stat.json group, spec).
    fn release_groups() -> Vec<ActionSpec> {
        vec![ActionSpec::joint_abs(), ActionSpec::joint_delta(), ActionSpec::eef_abs(), ActionSpec::eef_delta()]
    }

    #[test]
    fn bundled_stat_json_against_the_bundled_episodes() {
        let ds = open_dataset(&demo_root()).unwrap();
        let all: Vec<usize> = (0..ds.episodes().len()).collect();
        let specs = release_groups();
        let result = compute_stats(ds.as_ref(), &all, &specs, Some(&Default::default())).unwrap();
        assert_eq!(result.report.used, 3);
        assert_eq!(result.frames, 143 + 150 + 143);
        // Reported, not asserted: the release's statistics were computed over a larger set.
        eprintln!("bundled stat.json minus statistics of the 3 bundled episodes ({} frames), max |difference| per field:", result.frames);
        for (group, computed) in &result.groups {
            let bundled = ActionStats::read(&demo_root().join("stat.json"), group).unwrap();
            assert_eq!((bundled.dim(), computed.dim()), (14, 14), "{group}");
            let fields = [
                ("min", &bundled.min, &computed.min),
                ("max", &bundled.max, &computed.max),
                ("p01", &bundled.p01, &computed.p01),
                ("p99", &bundled.p99, &computed.p99),
                ("mean", &bundled.mean, &computed.mean),
                ("std", &bundled.std, &computed.std),
            ];
            let line: Vec<String> = fields
                .iter()
                .map(|(name, b, c)| {
                    let (i, d) = b.iter().zip(c.iter()).map(|(x, y)| (x - y).abs()).enumerate().fold((0, 0.0), |m, (i, d)| if d > m.1 { (i, d) } else { m });
                    format!("{name} {d:.4} (dim {i})")
                })
                .collect();
            eprintln!("  {group:>12}: {}", line.join(", "));
            assert!(computed.p01.iter().zip(&computed.p99).all(|(a, b)| a <= b));
        }

        // Written in the release's format, read back for normalization.
        let dir = tmp_dir("bundled-stats");
        let path = dir.join("stat.json");
        write_stat_json(&path, &result.groups).unwrap();
        let back = ActionStats::read(&path, "state_pose").unwrap();
        assert_eq!(back, result.groups[2].1);
        let first = ds.vectors(0, &ActionSpec::eef_abs()).unwrap();
        assert!(back.normalize(&first[0]).iter().all(|v| (-1.0..=1.0).contains(v)));

        // Training split only: a held-out episode changes the statistics.
        let split = split_episodes(ds.episodes(), &SplitSpec { seed: 1, validation: ValidationSize::Count(1) }).unwrap();
        assert_eq!((split.train.len(), split.validation.len()), (2, 1));
        let train = compute_stats(ds.as_ref(), &split.train, &specs[2..3], None).unwrap();
        assert_eq!(train.report.used, 2);
        assert_ne!(train.groups[0].1, result.groups[2].1);
    }
}
