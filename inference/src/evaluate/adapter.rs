//! Policy commands to world-model actions. The model takes absolute end-effector poses (raw
//! units, its action layout, normalized later with the training statistics); a policy may
//! command absolute poses (`eef_abs`), pose deltas (`eef_delta`, integrated from the last
//! commanded pose) or joint positions (`joint`, through a forward-kinematics program). The state
//! a policy is shown is its own last command: the pose for the eef adapters, the joints for
//! `joint`.

use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

use anyhow::{bail, ensure, Context, Result};

use super::config::{AdapterConfig, AdapterKind, FkConfig};

/// A running forward-kinematics program: one JSON line `{"joints": [[...], ...]}` in, one line
/// `{"poses": [[...], ...]}` out.
pub struct Fk {
    name: String,
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
}

impl Fk {
    pub fn start(cfg: &FkConfig) -> Result<Self> {
        let (program, args) = cfg.command.split_first().context("[fk] command is empty")?;
        let name = cfg.command.join(" ");
        let mut child = Command::new(program)
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .with_context(|| format!("starting the forward-kinematics command '{name}'"))?;
        let stdin = child.stdin.take().context("fk stdin")?;
        let stdout = BufReader::new(child.stdout.take().context("fk stdout")?);
        Ok(Self {
            name,
            child,
            stdin,
            stdout,
        })
    }

    /// Poses of joint vectors, one per row.
    pub fn poses(&mut self, joints: &[Vec<f32>]) -> Result<Vec<Vec<f32>>> {
        let what = || format!("forward kinematics '{}'", self.name);
        let request = serde_json::json!({ "joints": joints });
        writeln!(self.stdin, "{request}")
            .and_then(|_| self.stdin.flush())
            .with_context(|| format!("{}: writing", what()))?;
        let mut line = String::new();
        let n = self
            .stdout
            .read_line(&mut line)
            .with_context(|| format!("{}: reading", what()))?;
        ensure!(n > 0, "{}: the program exited", what());
        let reply: serde_json::Value = serde_json::from_str(&line)
            .with_context(|| format!("{}: reply is not JSON: {}", what(), line.trim()))?;
        if let Some(e) = reply.get("error") {
            bail!("{}: {e}", what());
        }
        let poses: Vec<Vec<f32>> = serde_json::from_value(
            reply.get("poses").cloned().unwrap_or_default(),
        )
        .with_context(|| {
            format!(
                "{}: expected {{\"poses\": [[numbers]]}}, got {}",
                what(),
                line.trim()
            )
        })?;
        ensure!(
            poses.len() == joints.len(),
            "{}: {} joint vectors in, {} poses out",
            what(),
            joints.len(),
            poses.len()
        );
        Ok(poses)
    }
}

impl Drop for Fk {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub struct Adapter {
    kind: AdapterKind,
    /// Positions of the command in the policy's action vector.
    indices: Vec<usize>,
    /// eef_delta: command positions not integrated.
    absolute: Vec<bool>,
    /// The last command, in the policy's space (what the policy is shown as its state).
    state: Vec<f32>,
    /// The last commanded pose, in the model's action layout.
    pose: Vec<f32>,
}

impl Adapter {
    /// An adapter at an episode's start: `pose` (eef adapters) or `joints` (joint) is the
    /// initial state; `action_dim` is the model's.
    pub fn new(
        cfg: &AdapterConfig,
        action_dim: usize,
        pose: Option<&[f32]>,
        joints: Option<&[f32]>,
        fk: Option<&mut Fk>,
    ) -> Result<Self> {
        let (state, pose) = match cfg.kind {
            AdapterKind::EefAbs | AdapterKind::EefDelta => {
                let pose = pose.context("the eef adapters need the initial pose (dataset pose vector or the start's pose file)")?;
                (pose.to_vec(), pose.to_vec())
            }
            AdapterKind::Joint => {
                let joints = joints.context("the joint adapter needs the initial joints (dataset joint vector or the start's joints file)")?;
                let fk = fk.context("the joint adapter needs the [fk] provider")?;
                let pose = fk.poses(&[joints.to_vec()])?.remove(0);
                (joints.to_vec(), pose)
            }
        };
        ensure!(
            pose.len() == action_dim,
            "the initial pose has {} values; the model takes {action_dim} action values",
            pose.len()
        );
        let dim = state.len();
        let indices = cfg.indices.clone().unwrap_or_else(|| (0..dim).collect());
        ensure!(
            indices.len() == dim,
            "adapter.indices selects {} values; the command ({}) has {dim}",
            indices.len(),
            if cfg.kind == AdapterKind::Joint {
                "joints"
            } else {
                "pose"
            }
        );
        let mut absolute = vec![false; dim];
        for &p in &cfg.absolute {
            ensure!(
                p < dim,
                "adapter.absolute position {p} is outside the {dim}-value command"
            );
            absolute[p] = true;
        }
        ensure!(
            state.iter().chain(&pose).all(|v| v.is_finite()),
            "the initial state holds NaN or infinite values"
        );
        Ok(Self {
            kind: cfg.kind,
            indices,
            absolute,
            state,
            pose,
        })
    }

    pub fn state(&self) -> &[f32] {
        &self.state
    }

    pub fn pose(&self) -> &[f32] {
        &self.pose
    }

    /// Executes policy action rows in order: returns the commanded pose of each (raw units) and
    /// advances the state.
    pub fn apply(&mut self, rows: &[Vec<f32>], fk: Option<&mut Fk>) -> Result<Vec<Vec<f32>>> {
        let need = self.indices.iter().max().map_or(0, |m| m + 1);
        let mut commands = Vec::with_capacity(rows.len());
        for (t, row) in rows.iter().enumerate() {
            ensure!(
                row.len() >= need,
                "the policy's actions have {} values; adapter.indices needs at least {need}",
                row.len()
            );
            let cmd: Vec<f32> = self.indices.iter().map(|&i| row[i]).collect();
            ensure!(
                cmd.iter().all(|v| v.is_finite()),
                "action {t} of the policy's chunk holds NaN or infinite values"
            );
            commands.push(cmd);
        }
        let poses = match self.kind {
            AdapterKind::EefAbs => commands.clone(),
            AdapterKind::EefDelta => {
                let mut pose = self.pose.clone();
                commands
                    .iter()
                    .map(|d| {
                        for (i, v) in d.iter().enumerate() {
                            pose[i] = if self.absolute[i] { *v } else { pose[i] + v };
                        }
                        pose.clone()
                    })
                    .collect()
            }
            AdapterKind::Joint => {
                let poses = fk
                    .context("the joint adapter needs the [fk] provider")?
                    .poses(&commands)?;
                if let Some((t, p)) = poses
                    .iter()
                    .enumerate()
                    .find(|(_, p)| p.len() != self.pose.len())
                {
                    bail!("forward kinematics gave a {}-value pose for action {t}; the model takes {}", p.len(), self.pose.len());
                }
                poses
            }
        };
        if let Some(last) = poses.last() {
            self.pose = last.clone();
            self.state = match self.kind {
                AdapterKind::Joint => commands.last().cloned().unwrap_or_default(),
                _ => last.clone(),
            };
        }
        Ok(poses)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(kind: AdapterKind, indices: Option<Vec<usize>>, absolute: Vec<usize>) -> AdapterConfig {
        AdapterConfig {
            kind,
            indices,
            absolute,
        }
    }

    #[test]
    fn eef_abs_selects_and_the_state_is_the_last_command() {
        let mut a = Adapter::new(
            &cfg(AdapterKind::EefAbs, Some(vec![2, 0]), vec![]),
            2,
            Some(&[1.0, 2.0]),
            None,
            None,
        )
        .unwrap();
        let poses = a
            .apply(&[vec![10.0, 0.0, 30.0], vec![11.0, 0.0, 31.0]], None)
            .unwrap();
        assert_eq!(poses, vec![vec![30.0, 10.0], vec![31.0, 11.0]]);
        assert_eq!(a.state(), &[31.0, 11.0]);
        let err = a.apply(&[vec![1.0, 2.0]], None).unwrap_err().to_string();
        assert!(err.contains("at least 3"), "{err}");
        assert!(a.apply(&[vec![f32::NAN, 0.0, 0.0]], None).is_err());
    }

    #[test]
    fn eef_delta_integrates_from_the_last_commanded_pose_except_absolute_positions() {
        let mut a = Adapter::new(
            &cfg(AdapterKind::EefDelta, None, vec![1]),
            2,
            Some(&[1.0, 0.0]),
            None,
            None,
        )
        .unwrap();
        let poses = a.apply(&[vec![0.5, 1.0], vec![0.25, 0.0]], None).unwrap();
        assert_eq!(poses, vec![vec![1.5, 1.0], vec![1.75, 0.0]]);
        assert_eq!(a.state(), &[1.75, 0.0]);
        let poses = a.apply(&[vec![-1.0, 1.0]], None).unwrap();
        assert_eq!(poses, vec![vec![0.75, 1.0]]);
    }

    #[test]
    fn joint_goes_through_the_fk_program_and_the_state_stays_in_joints() {
        let script = "import sys, json\nfor line in sys.stdin:\n    j = json.loads(line)['joints']\n    print(json.dumps({'poses': [[2 * v for v in r] + [sum(r)] for r in j]}), flush=True)\n";
        let mut fk = Fk::start(&FkConfig {
            command: vec!["python3".into(), "-c".into(), script.into()],
        })
        .unwrap();
        let mut a = Adapter::new(
            &cfg(AdapterKind::Joint, None, vec![]),
            3,
            None,
            Some(&[1.0, 2.0]),
            Some(&mut fk),
        )
        .unwrap();
        assert_eq!(a.pose(), &[2.0, 4.0, 3.0]);
        let poses = a
            .apply(&[vec![0.5, 0.5], vec![1.0, 3.0]], Some(&mut fk))
            .unwrap();
        assert_eq!(poses, vec![vec![1.0, 1.0, 1.0], vec![2.0, 6.0, 4.0]]);
        assert_eq!(a.state(), &[1.0, 3.0]);
        assert_eq!(a.pose(), &[2.0, 6.0, 4.0]);
        let err = Adapter::new(
            &cfg(AdapterKind::Joint, None, vec![]),
            4,
            None,
            Some(&[1.0, 2.0]),
            Some(&mut fk),
        )
        .err()
        .unwrap();
        assert!(err.to_string().contains("model takes 4"), "{err}");
    }
}
