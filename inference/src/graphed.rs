//! The sampler's forward pass recorded as a CUDA graph and replayed (`--cuda-graph`): a small
//! world model's denoising step is bound by launching its kernels, which a replay launches at once.
//! One graph per shape of the step's inputs (the batch of episodes in flight shrinks as they end),
//! up to `MAX_SHAPES`; shapes beyond run eagerly.

use anyhow::{Context, Result};
use bwm_cuda_graph::GraphedStep;
use bwm_model::sampler::{Denoiser, Eager};
use bwm_model::BwmModel;
use tch::{Device, Tensor};

/// Graphs kept at once: each holds its own memory pool of the forward pass's activations.
pub const MAX_SHAPES: usize = 4;

/// Eager runs on a new shape's graph stream before its capture (see `CudaGraph::warm_up`).
const WARM_UPS: u32 = 1;

type Shape = Vec<Vec<i64>>;

pub struct GraphedDenoiser {
    device: Device,
    graphs: Vec<(Shape, GraphedStep)>,
}

impl GraphedDenoiser {
    /// A denoiser for a model on `device`; an error unless it is a CUDA device.
    pub fn new(device: Device) -> Result<Self> {
        anyhow::ensure!(device.is_cuda(), "--cuda-graph needs a CUDA device, not {device:?}");
        Ok(Self { device, graphs: Vec::new() })
    }

    /// Shapes recorded (or warming up) so far.
    pub fn shapes(&self) -> usize {
        self.graphs.len()
    }
}

impl Denoiser for GraphedDenoiser {
    fn velocity(&mut self, model: &BwmModel, latents: &Tensor, frame_timesteps: &Tensor, actions: &Tensor, keep: Option<&Tensor>) -> Result<Tensor> {
        let mut inputs = vec![latents, frame_timesteps, actions];
        inputs.extend(keep);
        let shape: Shape = inputs.iter().map(|t| t.size()).collect();
        let slot = match self.graphs.iter().position(|(s, _)| *s == shape) {
            Some(i) => i,
            None if self.graphs.len() < MAX_SHAPES => {
                self.graphs.push((shape.clone(), GraphedStep::new(self.device, WARM_UPS)?));
                self.graphs.len() - 1
            }
            None => return Eager.velocity(model, latents, frame_timesteps, actions, keep),
        };
        self.graphs[slot]
            .1
            .run(&inputs, |t| model.forward_keeping(&t[0], &t[1], &t[2], t.get(3)))
            .with_context(|| format!("the sampler's forward pass as a CUDA graph (inputs {shape:?})"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bwm_model::rollout::{Rollout, RolloutSpec};
    use bwm_model::vae::{VaeConfig, WanVae};
    use bwm_model::vb::with_seed;
    use bwm_model::ModelConfig;
    use std::cell::RefCell;
    use std::rc::Rc;
    use tch::Kind;

    #[test]
    fn a_cpu_device_is_refused_by_name() {
        let err = GraphedDenoiser::new(Device::Cpu).err().expect("a CPU denoiser graph must be refused").to_string();
        assert!(err.contains("--cuda-graph needs a CUDA device"), "{err}");
    }

    /// On a CUDA machine (scripts/gpu/unit.sh; run with `--ignored` where libtorch sees no CUDA
    /// device, it fails when BWM_REQUIRE names cuda and is logged as skipped otherwise): batched
    /// rollouts of the tiny model whose sampler replays recorded graphs generate what the eager
    /// sampler generates, over chunks whose batch shrinks (a new shape, a new graph) and with
    /// guidance (the doubled batch and its keep mask as one more input); also with the hand map
    /// (its output layer drawn, so that its term counts), whose forward must read nothing from
    /// the host while a graph records.
    #[test]
    #[ignore = "needs a CUDA device (scripts/gpu/unit.sh)"]
    fn graphed_rollouts_generate_what_eager_ones_do() {
        if !bwm_testdir::need(bwm_testdir::Dep::Cuda, (!tch::Cuda::is_available()).then(|| "libtorch sees no CUDA device".to_string())) {
            return;
        }
        for hand_map in [None, Some(bwm_model::config::HandMapConfig { hands: vec![[0, 1, 2]], periods: 3 })] {
            graphed_rollouts_match_eager(hand_map);
        }
    }

    fn graphed_rollouts_match_eager(hand_map: Option<bwm_model::config::HandMapConfig>) {
        let device = Device::Cuda(0);
        let mut cfg = ModelConfig::preset("tiny").unwrap();
        let mapped = hand_map.is_some();
        cfg.action.hand_map = hand_map;
        let model = BwmModel::random(&cfg, Kind::Float, device, 3).unwrap();
        if let Some(map) = &model.action_encoder.hand_map {
            tch::no_grad(|| {
                let _ = map.mlp.l2.weight.shallow_clone().normal_(0.0, 0.1);
            });
        }
        let vae = WanVae::random(&VaeConfig::with_width(16, 16), Kind::Float, device, 4).unwrap().0;
        let d = cfg.action.action_dim;
        let (x0s, actions) = with_seed(5, || {
            let x0s: Vec<Tensor> = (0..3).map(|_| Tensor::rand([3, 32, 32], (Kind::Float, Device::Cpu)) * 2.0 - 1.0).collect();
            // Rollout 2 ends after one chunk: the second round runs a batch of two.
            let lengths = [8, 8, 4];
            let actions: Vec<Tensor> = lengths.iter().map(|&n| Tensor::rand([n, d], (Kind::Float, Device::Cpu)) * 2.0 - 1.0).collect();
            (x0s, actions)
        });
        for guidance in [1.0, 2.0] {
            let spec = RolloutSpec { steps: 3, guidance, ..RolloutSpec::new(4, 4) };
            let run = |graphed: Option<Rc<RefCell<GraphedDenoiser>>>| -> Vec<Tensor> {
                let mut rollouts: Vec<Rollout> = x0s
                    .iter()
                    .enumerate()
                    .map(|(i, x0)| {
                        let r = Rollout::new(&model, &vae, RolloutSpec { seed: i as u64, ..spec.clone() }, x0, &actions[i].get(0)).unwrap();
                        match &graphed {
                            Some(g) => r.with_denoiser(g.clone()),
                            None => r,
                        }
                    })
                    .collect();
                let mut frames: Vec<Vec<Tensor>> = (0..x0s.len()).map(|_| Vec::new()).collect();
                Rollout::run_together(&mut rollouts.iter_mut().collect::<Vec<_>>(), &actions, &mut |i, c| {
                    frames[i].push(c.frames);
                    Ok(())
                })
                .unwrap();
                frames.into_iter().map(|f| Tensor::cat(&f, 1)).collect()
            };
            let eager = run(None);
            let graphed = Rc::new(RefCell::new(GraphedDenoiser::new(device).unwrap()));
            let replayed = run(Some(graphed.clone()));
            assert_eq!(graphed.borrow().shapes(), 2, "a batch of three, then of two");
            for (i, (e, g)) in eager.iter().zip(&replayed).enumerate() {
                let diff = (e - g).abs().max().double_value(&[]);
                assert!(diff < 1e-4, "hand map {mapped}, guidance {guidance}, rollout {i}: graphed frames differ from eager ones by {diff}");
            }
        }
    }
}
