//! The action definition: which per-frame column and which of its indices form the action vector,
//! in order, and the optional explicit conversions applied after the selection.

use anyhow::{ensure, Context, Result};
use serde::{Deserialize, Serialize};

use crate::defect::{defect, DefectKind};

/// Which column and which of its indices form the action vector, in order, then optional
/// conversions:
///
/// 1. `indices` pick values from each row of `column`;
/// 2. each `quat_to_euler` entry replaces the 4 quaternion values at `start..start+4` of that
///    selection with roll, pitch, yaw (3 values), so the vector shrinks by one per entry;
///    `start` counts positions of the selection of step 1;
/// 3. the positions in `absolute_to_delta` (positions of the vector after step 2) become
///    frame-to-frame differences: `d[t] = x[t] - x[t-1]`, `d[0] = 0` (angles are not wrapped).
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ActionSpec {
    pub column: String,
    pub indices: Vec<usize>,
    /// The stat.json group holding this vector's statistics.
    pub stats_group: String,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub quat_to_euler: Vec<QuatToEuler>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub absolute_to_delta: Vec<usize>,
}

/// A unit quaternion at positions `start..start+4` turned into roll, pitch, yaw (radians) in the
/// static-axes x-y-z convention: R = Rz(yaw) * Ry(pitch) * Rx(roll), i.e. transforms3d's
/// `quat2euler(q, 'sxyz')` and scipy's `Rotation.as_euler('xyz')`. Roll and yaw are in
/// (-pi, pi], pitch in [-pi/2, pi/2]. The quaternion is normalized first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct QuatToEuler {
    pub start: usize,
    #[serde(default)]
    pub order: QuatOrder,
}

/// Component order of a stored quaternion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum QuatOrder {
    /// x, y, z, w (scipy, ROS).
    #[default]
    Xyzw,
    /// w, x, y, z (transforms3d, RoboTwin's `endpose`).
    Wxyz,
}

/// BWM's `JOINT_AND_EEF_NAMES` layout of the 26-wide `observation.state` / `action` rows:
/// the 14 joint-space positions (L joints 1-6, L gripper, R joints 1-6, R gripper).
const BWM_JOINT: [usize; 14] = [0, 1, 2, 3, 4, 5, 6, 13, 14, 15, 16, 17, 18, 19];
/// The 14 end-effector positions: L xyz, L euler xyz, L gripper, R xyz, R euler xyz, R gripper.
const BWM_EEF: [usize; 14] = [7, 8, 9, 10, 11, 12, 6, 20, 21, 22, 23, 24, 25, 19];

impl ActionSpec {
    /// BWM's `eef_abs`: absolute end-effector poses read from `observation.state`:
    /// left xyz, left euler, left gripper, right xyz, right euler, right gripper.
    pub fn eef_abs() -> Self {
        Self::plain("observation.state", &BWM_EEF, "state_pose")
    }

    /// BWM's `joint_abs`: joint positions and grippers from `observation.state`.
    pub fn joint_abs() -> Self {
        Self::plain("observation.state", &BWM_JOINT, "state_joint")
    }

    /// BWM's `eef_delta`: the end-effector values of the `action` column.
    pub fn eef_delta() -> Self {
        Self::plain("action", &BWM_EEF, "action_pose")
    }

    /// BWM's `joint_delta`: the joint values of the `action` column.
    pub fn joint_delta() -> Self {
        Self::plain("action", &BWM_JOINT, "action_joint")
    }

    /// RoboTwin's end poses in BWM's `eef_abs` order: the source's `endpose` column
    /// ([L x y z qw qx qy qz, L gripper, R x y z qw qx qy qz, R gripper]) with both quaternions
    /// turned into roll/pitch/yaw.
    pub fn robotwin_eef_abs() -> Self {
        Self {
            quat_to_euler: vec![
                QuatToEuler { start: 3, order: QuatOrder::Wxyz },
                QuatToEuler { start: 11, order: QuatOrder::Wxyz },
            ],
            ..Self::plain("endpose", &(0..16).collect::<Vec<_>>(), "state_pose")
        }
    }

    /// A preset by BWM's action type name (`eef_abs`, `joint_abs`, `eef_delta`, `joint_delta`,
    /// or the stat.json group names they alias) or `robotwin_eef_abs`.
    pub fn preset(name: &str) -> Result<Self> {
        Ok(match name {
            "eef_abs" | "state_pose" => Self::eef_abs(),
            "joint_abs" | "state_joint" => Self::joint_abs(),
            "eef_delta" | "action_pose" => Self::eef_delta(),
            "joint_delta" | "action_joint" => Self::joint_delta(),
            "robotwin_eef_abs" => Self::robotwin_eef_abs(),
            _ => anyhow::bail!(
                "unknown action preset '{name}' (presets: eef_abs, joint_abs, eef_delta, joint_delta, robotwin_eef_abs)"
            ),
        })
    }

    /// An action definition as users write it: a preset name, `COLUMN:INDICES` (e.g.
    /// `observation.state:0-5,7`; statistics under the column's name), or a JSON file holding an
    /// action spec.
    pub fn parse(arg: &str) -> Result<Self> {
        if arg.ends_with(".json") {
            let text = std::fs::read_to_string(arg).with_context(|| format!("action spec: reading {arg}"))?;
            let spec: Self = serde_json::from_str(&text).with_context(|| format!("{arg} is not an action spec"))?;
            spec.validate().with_context(|| format!("action spec {arg}"))?;
            return Ok(spec);
        }
        let Some((column, list)) = arg.split_once(':') else { return Self::preset(arg) };
        let mut indices = Vec::new();
        for part in list.split(',').map(str::trim) {
            let parse = |s: &str| s.trim().parse::<usize>().with_context(|| format!("actions {arg}: '{s}' is not an index"));
            match part.split_once('-') {
                Some((lo, hi)) => {
                    let (lo, hi) = (parse(lo)?, parse(hi)?);
                    ensure!(lo <= hi, "actions {arg}: range {lo}-{hi} is reversed");
                    indices.extend(lo..=hi);
                }
                None => indices.push(parse(part)?),
            }
        }
        ensure!(!column.is_empty(), "actions {arg}: no column name before ':'");
        let spec = Self::plain(column, &indices, column);
        spec.validate().with_context(|| format!("actions {arg}"))?;
        Ok(spec)
    }

    fn plain(column: &str, indices: &[usize], stats_group: &str) -> Self {
        Self {
            column: column.into(),
            indices: indices.to_vec(),
            stats_group: stats_group.into(),
            quat_to_euler: Vec::new(),
            absolute_to_delta: Vec::new(),
        }
    }

    /// Length of the final action vector.
    pub fn dim(&self) -> usize {
        self.indices.len() - self.quat_to_euler.len()
    }

    /// Checks that the conversions fit the selection: quaternions inside it and not
    /// overlapping, delta positions inside the converted vector and not repeated.
    pub fn validate(&self) -> Result<()> {
        ensure!(!self.indices.is_empty(), "action spec for column '{}' selects no indices", self.column);
        let mut quats: Vec<_> = self.quat_to_euler.iter().map(|q| q.start).collect();
        quats.sort_unstable();
        for (i, &s) in quats.iter().enumerate() {
            ensure!(
                s.checked_add(4).is_some_and(|end| end <= self.indices.len()),
                "quat_to_euler start {s}: positions {s}..{s}+4 lie outside the {} selected indices",
                self.indices.len()
            );
            if let Some(&next) = quats.get(i + 1) {
                ensure!(next >= s + 4, "quat_to_euler starts {s} and {next} overlap");
            }
        }
        let dim = self.dim();
        let mut deltas = self.absolute_to_delta.clone();
        deltas.sort_unstable();
        for (i, &p) in deltas.iter().enumerate() {
            ensure!(p < dim, "absolute_to_delta position {p} is outside the {dim}-wide converted vector");
            ensure!(deltas.get(i + 1) != Some(&p), "absolute_to_delta lists position {p} twice");
        }
        Ok(())
    }

    /// Applies the selection and conversions to the rows of `column` (one row per frame).
    /// `what` names the data in messages (e.g. the file). A NaN/inf selected value is a
    /// `NonFinite` defect naming the row.
    pub fn apply(&self, rows: &[Vec<f32>], what: &str) -> Result<Vec<Vec<f32>>> {
        self.validate()?;
        let mut out = Vec::with_capacity(rows.len());
        for (i, row) in rows.iter().enumerate() {
            let mut v = Vec::with_capacity(self.indices.len());
            for &j in &self.indices {
                let Some(&x) = row.get(j) else {
                    return defect(
                        DefectKind::UnknownColumn,
                        format!("{what}: row {i} of '{}' has {} values, index {j} requested", self.column, row.len()),
                    );
                };
                if !x.is_finite() {
                    return defect(
                        DefectKind::NonFinite,
                        format!("{what}: row {i} of '{}' holds a non-finite value ({x}) at index {j}", self.column),
                    );
                }
                v.push(x);
            }
            out.push(self.convert_row(v, i, what)?);
        }
        for &p in &self.absolute_to_delta {
            for t in (1..out.len()).rev() {
                out[t][p] -= out[t - 1][p];
            }
            if let Some(first) = out.first_mut() {
                first[p] = 0.0;
            }
        }
        Ok(out)
    }

    /// What each value of the final action vector means, in order: the named components of BWM's
    /// presets (`left x`, ..., `right gripper`), else `COLUMN[i]` per selected index, a converted
    /// quaternion as its roll, pitch and yaw, and `(change since the previous frame)` after the
    /// values `absolute_to_delta` turns into differences.
    pub fn components(&self) -> Vec<String> {
        const EEF: [&str; 7] = ["x", "y", "z", "roll", "pitch", "yaw", "gripper"];
        const JOINT: [&str; 7] = ["joint 1", "joint 2", "joint 3", "joint 4", "joint 5", "joint 6", "gripper"];
        let sides = |names: [&str; 7]| ["left", "right"].iter().flat_map(|s| names.iter().map(move |n| format!("{s} {n}"))).collect::<Vec<_>>();
        if *self == Self::eef_abs() || *self == Self::eef_delta() || *self == Self::robotwin_eef_abs() {
            return sides(EEF);
        }
        if *self == Self::joint_abs() || *self == Self::joint_delta() {
            return sides(JOINT);
        }
        let mut names: Vec<String> = self.indices.iter().map(|i| format!("{}[{i}]", self.column)).collect();
        let mut quats = self.quat_to_euler.clone();
        quats.sort_unstable_by_key(|q| std::cmp::Reverse(q.start));
        for q in quats {
            let s = q.start;
            let source = format!("{}[{}]", self.column, self.indices[s..s + 4].iter().map(|i| i.to_string()).collect::<Vec<_>>().join(","));
            names.splice(s..s + 4, ["roll", "pitch", "yaw"].map(|a| format!("{a} of the quaternion {source}")));
        }
        for &p in &self.absolute_to_delta {
            if let Some(n) = names.get_mut(p) {
                n.push_str(" (change since the previous frame)");
            }
        }
        names
    }

    fn convert_row(&self, mut v: Vec<f32>, row: usize, what: &str) -> Result<Vec<f32>> {
        let mut quats = self.quat_to_euler.clone();
        quats.sort_unstable_by_key(|q| std::cmp::Reverse(q.start));
        for q in quats {
            let s = q.start;
            let raw = [v[s], v[s + 1], v[s + 2], v[s + 3]];
            let Some(rpy) = quat_to_rpy(raw, q.order) else {
                return defect(
                    DefectKind::NonFinite,
                    format!("{what}: row {row} of '{}': the quaternion at positions {s}..{} has zero length", self.column, s + 4),
                );
            };
            v.splice(s..s + 4, rpy);
        }
        Ok(v)
    }
}

/// Roll, pitch, yaw of a quaternion (see `QuatToEuler`), computed in f64. None for a zero or
/// non-finite quaternion.
pub fn quat_to_rpy(q: [f32; 4], order: QuatOrder) -> Option<[f32; 3]> {
    let [a, b, c, d] = q.map(f64::from);
    let (w, x, y, z) = match order {
        QuatOrder::Xyzw => (d, a, b, c),
        QuatOrder::Wxyz => (a, b, c, d),
    };
    let n = (w * w + x * x + y * y + z * z).sqrt();
    if !n.is_finite() || n < 1e-12 {
        return None;
    }
    let (w, x, y, z) = (w / n, x / n, y / n, z / n);
    let roll = (2.0 * (w * x + y * z)).atan2(1.0 - 2.0 * (x * x + y * y));
    let pitch = (2.0 * (w * y - z * x)).clamp(-1.0, 1.0).asin();
    let yaw = (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z));
    Some([roll as f32, pitch as f32, yaw as f32])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_conversion_outside_the_selection_is_refused_however_far() {
        for start in [2, usize::MAX - 1] {
            let spec = ActionSpec { quat_to_euler: vec![QuatToEuler { start, order: QuatOrder::Xyzw }], ..ActionSpec::parse("pose:0-4").unwrap() };
            let err = spec.validate().unwrap_err().to_string();
            assert!(err.contains(&format!("quat_to_euler start {start}: positions")), "{err}");
        }
    }

    #[test]
    fn parse_reads_presets_column_indices_and_refuses_bad_lists() {
        assert_eq!(ActionSpec::parse("eef_abs").unwrap(), ActionSpec::eef_abs());
        let spec = ActionSpec::parse("observation.state:0-2,5").unwrap();
        assert_eq!((spec.column.as_str(), spec.indices.as_slice(), spec.stats_group.as_str()), ("observation.state", &[0, 1, 2, 5][..], "observation.state"));
        for bad in ["observation.state:3-1", "observation.state:a", ":0-3", "nonsense"] {
            assert!(ActionSpec::parse(bad).is_err(), "{bad} was accepted");
        }
        assert!(ActionSpec::parse("/nonexistent/spec.json").unwrap_err().to_string().contains("reading"));
    }
    use crate::defect::classify;

    /// q = qz(yaw) * qy(pitch) * qx(roll), as (w, x, y, z).
    fn quat_from_rpy(r: f64, p: f64, y: f64) -> [f64; 4] {
        let (cr, sr, cp, sp, cy, sy) = ((r / 2.0).cos(), (r / 2.0).sin(), (p / 2.0).cos(), (p / 2.0).sin(), (y / 2.0).cos(), (y / 2.0).sin());
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ]
    }

    /// Every component is named, as many as the vector has values: the presets by meaning, a
    /// column selection by index, conversions by what they do.
    #[test]
    fn components_name_every_value_in_order() {
        let eef = ActionSpec::eef_abs().components();
        assert_eq!((eef.len(), eef[0].as_str(), eef[6].as_str(), eef[13].as_str()), (14, "left x", "left gripper", "right gripper"));
        assert_eq!(ActionSpec::robotwin_eef_abs().components(), eef);
        assert_eq!(ActionSpec::joint_abs().components()[7], "right joint 1");
        assert_eq!(ActionSpec::parse("observation.state:0-3").unwrap().components(), ["observation.state[0]", "observation.state[1]", "observation.state[2]", "observation.state[3]"]);
        let spec = ActionSpec {
            quat_to_euler: vec![QuatToEuler { start: 1, order: QuatOrder::Xyzw }],
            absolute_to_delta: vec![0],
            ..ActionSpec::parse("pose:0-4").unwrap()
        };
        let c = spec.components();
        assert_eq!(c.len(), spec.dim());
        assert_eq!(c[0], "pose[0] (change since the previous frame)");
        assert_eq!(c[1], "roll of the quaternion pose[1,2,3,4]");
        assert_eq!(c[3], "yaw of the quaternion pose[1,2,3,4]");
    }

    #[test]
    fn quaternions_turn_into_static_xyz_euler_angles() {
        let half = std::f32::consts::FRAC_1_SQRT_2;
        // 90 degrees about z (w, x, y, z) = (cos 45, 0, 0, sin 45): yaw = pi/2.
        let rpy = quat_to_rpy([half, 0.0, 0.0, half], QuatOrder::Wxyz).unwrap();
        assert!((rpy[2] - std::f32::consts::FRAC_PI_2).abs() < 1e-6 && rpy[0].abs() < 1e-6 && rpy[1].abs() < 1e-6);
        // The same rotation stored x, y, z, w; and a non-unit quaternion is normalized.
        assert_eq!(quat_to_rpy([0.0, 0.0, 2.0 * half, 2.0 * half], QuatOrder::Xyzw).unwrap(), rpy);
        for &(r, p, y) in &[(0.3, -0.2, 1.1), (-2.5, 0.7, -3.0), (1.0, 1.2, 0.1), (3.0, -1.4, 2.9)] {
            let [w, x, yy, z] = quat_from_rpy(r, p, y).map(|v| v as f32);
            let got = quat_to_rpy([w, x, yy, z], QuatOrder::Wxyz).unwrap();
            let got_xyzw = quat_to_rpy([x, yy, z, w], QuatOrder::Xyzw).unwrap();
            assert_eq!(got, got_xyzw);
            for (g, e) in got.iter().zip([r, p, y]) {
                assert!((*g as f64 - e).abs() < 1e-5, "rpy ({r}, {p}, {y}) came back as {got:?}");
            }
        }
        assert!(quat_to_rpy([0.0; 4], QuatOrder::Wxyz).is_none());
        assert!(quat_to_rpy([f32::NAN, 0.0, 0.0, 1.0], QuatOrder::Wxyz).is_none());
    }

    #[test]
    fn conversions_apply_in_order() {
        let half = std::f32::consts::FRAC_1_SQRT_2;
        // Row: [x, qw, qx, qy, qz, g]: select all, convert the quaternion, delta on x.
        let spec = ActionSpec {
            column: "s".into(),
            indices: vec![0, 1, 2, 3, 4, 5],
            stats_group: "g".into(),
            quat_to_euler: vec![QuatToEuler { start: 1, order: QuatOrder::Wxyz }],
            absolute_to_delta: vec![0],
        };
        assert_eq!(spec.dim(), 5);
        let rows = vec![vec![1.0, 1.0, 0.0, 0.0, 0.0, 0.5], vec![1.5, half, 0.0, 0.0, half, 0.25], vec![3.5, 1.0, 0.0, 0.0, 0.0, 1.0]];
        let out = spec.apply(&rows, "t").unwrap();
        assert_eq!(out.len(), 3);
        assert_eq!(out[0], vec![0.0, 0.0, 0.0, 0.0, 0.5]);
        assert_eq!(out[1][0], 0.5);
        assert!((out[1][3] - std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        assert_eq!(out[2][0], 2.0);
        assert_eq!(out[2][4], 1.0);
    }

    #[test]
    fn bad_specs_and_rows_are_errors() {
        let mut spec = ActionSpec::robotwin_eef_abs();
        spec.validate().unwrap();
        assert_eq!(spec.dim(), 14);
        spec.quat_to_euler.push(QuatToEuler { start: 5, order: QuatOrder::Wxyz });
        assert!(spec.validate().unwrap_err().to_string().contains("overlap"));
        spec.quat_to_euler = vec![QuatToEuler { start: 13, order: QuatOrder::Wxyz }];
        assert!(spec.validate().unwrap_err().to_string().contains("outside"));
        let spec = ActionSpec { absolute_to_delta: vec![14], ..ActionSpec::eef_abs() };
        assert!(spec.validate().is_err());

        let spec = ActionSpec::eef_abs();
        let mut row = vec![0.0f32; 26];
        row[20] = f32::NAN;
        let e = spec.apply(&[vec![0.0; 26], row], "file.parquet").unwrap_err();
        assert_eq!(classify(&e), DefectKind::NonFinite);
        assert!(e.to_string().contains("row 1") && e.to_string().contains("file.parquet"), "{e}");
        let e = spec.apply(&[vec![0.0; 20]], "f").unwrap_err();
        assert_eq!(classify(&e), DefectKind::UnknownColumn);

        let json = r#"{"column": "c", "indices": [0, 1, 2, 3], "stats_group": "g", "quat_to_euler": [{"start": 0}]}"#;
        let spec: ActionSpec = serde_json::from_str(json).unwrap();
        assert_eq!(spec.quat_to_euler[0].order, QuatOrder::Xyzw);
        assert!(serde_json::from_str::<ActionSpec>(r#"{"column": "c", "indices": [], "stats_group": "g", "extra": 1}"#).is_err());
        assert_eq!(ActionSpec::preset("state_pose").unwrap(), ActionSpec::eef_abs());
        assert!(ActionSpec::preset("nope").is_err());
    }
}
