//! The WorldArena 2.0 environment API on `bwm serve`, beside its own `/v1/chunk`: the
//! model-agnostic world-model environment of WorldArena 2.0's RL benchmark
//! (`WorldArena2/WorldArena-2.0`, `RL_env_benchmark/README.md`; RLinf's `BaseWorldEnv` and its
//! HTTP server `wan_http_server.py`): `GET /health`, `POST /reset`, `POST /chunk_step`, a batch of
//! environments stepped together, observations under the keys `main_images`, `wrist_images`,
//! `states` and `task_descriptions`, and the reward (with termination and truncation) left to the
//! caller. That server wraps its dicts as pickle inside JSON ("for simplicity"; its README
//! recommends msgpack); here the bodies are msgpack maps with openpi's msgpack-numpy arrays, as
//! `/v1/chunk`'s, since unpickling a client's bytes runs the client's code.
//!
//! The environments live in the model worker between requests: `/reset` starts one rollout per
//! environment at its first frame and state, `/chunk_step` advances all of them by one chunk of
//! actions in one batch. A `/reset` replaces every environment.

use std::cell::RefCell;
use std::rc::Rc;

use bwm_model::rollout::Rollout;
use rmpv::Value;
use tch::{Kind, Tensor};

use super::{action_values, api, body_map, images, normalized_flag, seed_of, str_map, ApiError, ModelInfo, NdArray, Watch, Watched};
use crate::world_model::WorldModel;

/// A checked `/reset` body.
pub(super) struct ResetRequest {
    /// uint8 [N, H, W, 3]: each environment's first frame.
    images: Vec<u8>,
    n: usize,
    h: usize,
    w: usize,
    /// [N][d_a]: each first frame's state, the action vector of that frame, as sent.
    states: Vec<Vec<f32>>,
    tasks: Vec<String>,
    normalized: bool,
    seed: Option<u64>,
}

/// A checked `/chunk_step` body: [N][n][d_a] actions, as sent.
pub(super) struct StepRequest {
    actions: Vec<Vec<Vec<f32>>>,
}

impl StepRequest {
    /// The environments the actions are for.
    pub(super) fn len(&self) -> usize {
        self.actions.len()
    }
}

const RESET_KEYS: [&str; 5] = ["main_images", "states", "task_descriptions", "normalized", "seed"];

/// Checks a `/reset` body: `main_images` uint8 (N, H, W, 3), `states` float (N, d_a),
/// `task_descriptions` N strings (optional), `normalized` (optional, default false: raw states
/// and actions, normalized with the server's statistics), `seed` (optional).
pub(super) fn parse_reset(body: &[u8], info: &ModelInfo) -> Result<ResetRequest, ApiError> {
    let v = body_map(body, &RESET_KEYS)?;
    let (images, h, w) = images(&v, "main_images", 1, "(N, H, W, 3): each environment's first frame", info)?;
    let n = images.shape[0];
    if super::map_get(&v, "states").is_none() {
        let layout = info.contract.actions.as_ref().map(|a| a.components.join(", ")).filter(|c| !c.is_empty());
        return Err(api(
            422,
            format!(
                "'states' is missing: each environment's state at its first frame, float32 (N, {}){}",
                info.action_dim,
                layout.map(|l| format!(" in the model's action layout ({l})")).unwrap_or_default()
            ),
        ));
    }
    let (shape, values) = action_values(&v, "states", 2, "(N, d_a)", info)?;
    if shape[0] != n {
        return Err(api(422, format!("'states' has {} rows for {n} environments ('main_images')", shape[0])));
    }
    let tasks = match super::map_get(&v, "task_descriptions") {
        None | Some(Value::Nil) => vec![String::new(); n],
        Some(Value::Array(items)) if items.len() == n => items
            .iter()
            .map(|t| t.as_str().map(str::to_string).ok_or_else(|| api(422, format!("'task_descriptions' must hold strings, got {t}"))))
            .collect::<Result<_, _>>()?,
        Some(other) => return Err(api(422, format!("'task_descriptions' must be a list of {n} strings, got {other}"))),
    };
    Ok(ResetRequest {
        images: images.data,
        n,
        h,
        w,
        states: values.chunks(info.action_dim).map(<[f32]>::to_vec).collect(),
        tasks,
        normalized: normalized_flag(&v, Some(false), info)?,
        seed: seed_of(&v)?,
    })
}

/// Checks a `/chunk_step` body: `actions` float (N, n, d_a), 1 <= n <= K. The number of
/// environments is checked against the reset's by the worker.
pub(super) fn parse_step(body: &[u8], info: &ModelInfo) -> Result<StepRequest, ApiError> {
    let v = body_map(body, &["actions"])?;
    let (shape, values) = action_values(&v, "actions", 3, "(N, n, d_a): each environment's next actions", info)?;
    let (n, rows, d) = (shape[0], shape[1], shape[2]);
    if rows == 0 || rows > info.future {
        return Err(api(422, format!("'actions' has {rows} actions per environment; a chunk takes 1..={} (K)", info.future)));
    }
    let per_env = rows * d;
    let actions = (0..n).map(|e| values[e * per_env..(e + 1) * per_env].chunks(d).map(<[f32]>::to_vec).collect()).collect();
    Ok(StepRequest { actions })
}

/// The environments of the last `/reset`, kept by the model worker.
pub(super) struct Envs<'m> {
    rollouts: Vec<Rollout<'m>>,
    /// The sampler's forward passes of every environment, watched against each request's deadline.
    watched: Rc<RefCell<Watched>>,
    /// uint8 [N, H, W, 3]: each environment's newest frame.
    latest: Vec<u8>,
    h: usize,
    w: usize,
    /// Each environment's newest state (the last action applied), as sent.
    states: Vec<Vec<f32>>,
    tasks: Vec<String>,
    normalized: bool,
    elapsed_steps: usize,
}

/// The observation dict: `main_images` uint8 (N, H, W, 3), `wrist_images` nil, `states` float32
/// (N, d_a), `task_descriptions`.
fn observation(latest: &[u8], n: usize, h: usize, w: usize, states: &[Vec<f32>], tasks: &[String]) -> anyhow::Result<Value> {
    let d = states.first().map_or(0, Vec::len);
    let flat: Vec<f32> = states.iter().flatten().copied().collect();
    Ok(str_map(vec![
        ("main_images", NdArray::from_u8(vec![n, h, w, 3], latest.to_vec())?.to_value()),
        ("wrist_images", Value::Nil),
        ("states", NdArray::from_f32(vec![n, d], &flat)?.to_value()),
        ("task_descriptions", Value::Array(tasks.iter().map(|t| Value::from(t.as_str())).collect())),
    ]))
}

impl<'m> Envs<'m> {
    /// Starts one rollout per environment; the reply holds the observation.
    pub(super) fn reset(wm: &'m WorldModel, req: &ResetRequest) -> anyhow::Result<(Self, Vec<u8>)> {
        let frame = req.h * req.w * 3;
        let shape = [req.n as i64, req.h as i64, req.w as i64, 3];
        let x0 = Tensor::f_from_slice(&req.images)?.f_view(shape)?.f_permute([0, 3, 1, 2])?.f_to_kind(Kind::Float)?.f_div_scalar(127.5)?.f_sub_scalar(1.0)?;
        let a0 = if req.normalized { wm.rows_to_tensor(req.states.clone()) } else { wm.normalize(&req.states) }?;
        let watched = Rc::new(RefCell::new(Watched { inner: wm.graphed.clone(), watch: Watch { deadline: None, hold: None }, step: 0, steps: wm.spec.steps }));
        let seed = req.seed.unwrap_or(wm.spec.seed);
        let rollouts = (0..req.n)
            .map(|e| {
                // Each environment draws its own noise: the seed, offset by its position.
                let spec = bwm_model::rollout::RolloutSpec { seed: seed.wrapping_add(e as u64), ..wm.spec.clone() };
                Ok(wm.rollout_with(spec, &x0.get(e as i64), &a0.get(e as i64))?.with_denoiser(watched.clone()))
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        let envs = Self {
            rollouts,
            watched,
            latest: req.images[..req.n * frame].to_vec(),
            h: req.h,
            w: req.w,
            states: req.states.clone(),
            tasks: req.tasks.clone(),
            normalized: req.normalized,
            elapsed_steps: 0,
        };
        let out = str_map(vec![
            ("obs", observation(&envs.latest, req.n, req.h, req.w, &envs.states, &envs.tasks)?),
            ("num_envs", Value::from(req.n as u64)),
            ("elapsed_steps", Value::from(0u64)),
        ]);
        Ok((envs, super::msgpack_numpy::encode(&out)))
    }

    pub(super) fn len(&self) -> usize {
        self.rollouts.len()
    }

    /// Advances every environment by its actions, in one batch; the reply holds the observation
    /// after the chunk, every generated frame (`frames`, uint8 (N, n, H, W, 3)) and the steps
    /// taken since the reset.
    pub(super) fn step(&mut self, wm: &WorldModel, req: &StepRequest, watch: Watch) -> anyhow::Result<Vec<u8>> {
        let actions = req
            .actions
            .iter()
            .map(|rows| if self.normalized { wm.rows_to_tensor(rows.clone()) } else { wm.normalize(rows) })
            .collect::<anyhow::Result<Vec<_>>>()?;
        *self.watched.borrow_mut() = Watched { inner: wm.graphed.clone(), watch, step: 0, steps: wm.spec.steps };
        let chunks = Rollout::next_chunks(&mut self.rollouts.iter_mut().collect::<Vec<_>>(), &actions)?;
        let (n, rows) = (self.rollouts.len(), req.actions[0].len());
        let frame = self.h * self.w * 3;
        let mut frames = Vec::with_capacity(n * rows * frame);
        for (e, chunk) in chunks.iter().enumerate() {
            let pixels = bwm_data::frames::unit_to_u8(&chunk.frames).permute([1, 2, 3, 0]).contiguous();
            let pixels = Vec::<u8>::try_from(pixels.view([-1]))?;
            self.latest[e * frame..(e + 1) * frame].copy_from_slice(&pixels[(rows - 1) * frame..]);
            frames.extend_from_slice(&pixels);
            self.states[e] = req.actions[e][rows - 1].clone();
        }
        self.elapsed_steps += rows;
        let out = str_map(vec![
            ("obs", observation(&self.latest, n, self.h, self.w, &self.states, &self.tasks)?),
            ("frames", NdArray::from_u8(vec![n, rows, self.h, self.w, 3], frames)?.to_value()),
            ("elapsed_steps", Value::from(self.elapsed_steps as u64)),
        ]);
        Ok(super::msgpack_numpy::encode(&out))
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::{actions, frames, info};
    use super::*;

    fn encode(entries: Vec<(&str, Value)>) -> Vec<u8> {
        super::super::msgpack_numpy::encode(&str_map(entries))
    }

    fn err<T>(r: Result<T, ApiError>) -> String {
        match r {
            Err(e) => format!("{} {}", e.status, e.message),
            Ok(_) => "accepted".into(),
        }
    }

    /// A reset names what it lacks or gets wrong in one line: the state key, the batch, the
    /// strings; a step names its shape and chunk length.
    #[test]
    fn reset_and_step_bodies_are_checked() {
        let i = info();
        let good = || vec![("main_images", frames(2, 32, 32).to_value()), ("states", actions(2, 2).to_value()), ("normalized", Value::Boolean(true))];
        let r = parse_reset(&encode(good()), &i).unwrap();
        assert_eq!((r.n, r.h, r.w, r.states.len(), r.tasks.len()), (2, 32, 32, 2, 2));
        let e = err(parse_reset(&encode(vec![("main_images", frames(2, 32, 32).to_value()), ("normalized", Value::Boolean(true))]), &i));
        assert!(e.starts_with("422 'states' is missing") && e.contains("(N, 2)"), "{e}");
        let e = err(parse_reset(&encode(vec![("main_images", frames(2, 32, 32).to_value()), ("states", actions(3, 2).to_value()), ("normalized", Value::Boolean(true))]), &i));
        assert!(e.contains("3 rows for 2 environments"), "{e}");
        let e = err(parse_reset(&encode(vec![("main_images", frames(2, 32, 32).to_value()), ("states", actions(2, 7).to_value()), ("normalized", Value::Boolean(true))]), &i));
        assert!(e.contains("'states': 7-D actions, but this model takes 2-D"), "{e}");
        let mut bad_tasks = good();
        bad_tasks.push(("task_descriptions", Value::Array(vec![Value::from("open")])));
        assert!(err(parse_reset(&encode(bad_tasks), &i)).contains("a list of 2 strings"));
        let raw = vec![("main_images", frames(1, 32, 32).to_value()), ("states", actions(1, 2).to_value())];
        assert!(err(parse_reset(&encode(raw), &i)).contains("need the training statistics"), "raw states are the default, and this server has no statistics");

        let step = |a: NdArray| err(parse_step(&encode(vec![("actions", a.to_value())]), &i));
        let three = |n: usize, rows: usize, d: usize| NdArray::from_f32(vec![n, rows, d], &vec![0.1; n * rows * d]).unwrap();
        assert_eq!(step(three(2, 4, 2)), "accepted");
        assert!(step(three(2, 5, 2)).contains("1..=4 (K)"));
        assert!(step(actions(2, 2)).contains("must be (N, n, d_a)"));
    }
}
