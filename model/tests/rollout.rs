//! The rollout loop on the tiny model and a small random VAE (CPU): chunk shapes, seeded
//! determinism, x0 padding of the history at the episode start, the prefix held fixed through
//! every sampler step, the short last window, bf16.

use bwm_model::keyed_rng::{self, Purpose};
use bwm_model::rollout::{Rollout, RolloutSpec};
use bwm_model::vae::{VaeConfig, WanVae};
use bwm_model::{BwmModel, ModelConfig};
use tch::{Device, Kind, Tensor};

const SIDE: i64 = 32;

/// The tiny model and a small VAE with seeded random weights; one at a time, since the seed is
/// libtorch's global generator, shared by the test threads.
fn parts(kind: Kind) -> (BwmModel, WanVae) {
    static GLOBAL_GENERATOR: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _guard = GLOBAL_GENERATOR.lock().unwrap_or_else(|e| e.into_inner());
    let model = BwmModel::random(&ModelConfig::preset("tiny").unwrap(), kind, Device::Cpu, 3).unwrap();
    let (vae, _) = WanVae::random(&VaeConfig::with_width(16, 16), Kind::Float, Device::Cpu, 4).unwrap();
    (model, vae)
}

fn spec(history: usize, future: usize, seed: u64) -> RolloutSpec {
    RolloutSpec { steps: 3, seed, ..RolloutSpec::new(history, future) }
}

/// x0 [3, SIDE, SIDE], a0 [d] and `rows` actions, all in [-1, 1], from keyed draws (the tests run in
/// parallel threads, so libtorch's global generator would give each a different interleaving).
fn inputs(d: i64, rows: i64) -> (Tensor, Tensor, Tensor) {
    let draw = |shape: &[i64], key: u64| keyed_rng::normal(shape, 11, key, Purpose::Augment).tanh();
    (draw(&[3, SIDE, SIDE], 0), draw(&[d], 1), draw(&[rows, d], 2))
}

fn roll(model: &BwmModel, vae: &WanVae, spec: RolloutSpec, actions: &Tensor) -> Vec<(Tensor, Tensor)> {
    let d = model.cfg.action.action_dim;
    let (x0, a0, _) = inputs(d, 1);
    let mut r = Rollout::new(model, vae, spec, &x0, &a0).unwrap();
    let mut out = Vec::new();
    r.run(actions, &mut |c| {
        out.push((c.frames, c.actions));
        Ok(())
    })
    .unwrap();
    out
}

#[test]
fn chunks_have_the_asked_shapes_and_a_seed_fixes_them() {
    let (model, vae) = parts(Kind::Float);
    let d = model.cfg.action.action_dim;
    let (_, _, actions) = inputs(d, 10);
    let a = roll(&model, &vae, spec(4, 4, 5), &actions);
    assert_eq!(a.iter().map(|(f, _)| f.size()).collect::<Vec<_>>(), vec![vec![3, 4, SIDE, SIDE], vec![3, 4, SIDE, SIDE], vec![3, 2, SIDE, SIDE]]);
    let applied = Tensor::cat(&a.iter().map(|(_, a)| a.shallow_clone()).collect::<Vec<_>>(), 0);
    assert!(applied.equal(&actions), "each chunk carries the actions that drove it, row by row");
    for (f, _) in &a {
        assert!(f.max().double_value(&[]) <= 1.0 && f.min().double_value(&[]) >= -1.0);
    }
    let b = roll(&model, &vae, spec(4, 4, 5), &actions);
    assert!(a.iter().zip(&b).all(|(x, y)| x.0.equal(&y.0)), "same seed, same video");
    let c = roll(&model, &vae, spec(4, 4, 6), &actions);
    assert!(!a[0].0.equal(&c[0].0), "another seed, another video");
}

#[test]
fn history_is_padded_with_x0_and_a0_then_filled_with_what_was_shown() {
    let (model, vae) = parts(Kind::Float);
    let d = model.cfg.action.action_dim;
    let (x0, a0, actions) = inputs(d, 4);
    let mut r = Rollout::new(&model, &vae, spec(8, 4, 1), &x0, &a0).unwrap();
    let (frames, acts) = r.condition();
    assert_eq!(frames.size(), [3, 9, SIDE, SIDE]);
    for t in 0..9 {
        assert!(frames.select(1, t).equal(&x0) && acts.get(t).equal(&a0), "slot {t} before any frame is x0 / a0");
    }
    let chunk = r.next_chunk(&actions).unwrap();
    let (frames, acts) = r.condition();
    for t in 0..5 {
        assert!(frames.select(1, t).equal(&x0) && acts.get(t).equal(&a0), "slot {t} still padding");
    }
    assert!(frames.narrow(1, 5, 4).equal(&chunk.frames), "the generated frames become the history");
    assert!(acts.narrow(0, 5, 4).equal(&actions), "with the actions applied to them");

    // Given history replaces padding, newest last; only the last H are kept.
    let hist = keyed_rng::normal(&[3, 10, SIDE, SIDE], 12, 0, Purpose::Augment).tanh();
    let hist_actions = keyed_rng::normal(&[10, d], 12, 1, Purpose::Augment).tanh();
    let r = Rollout::new(&model, &vae, spec(8, 4, 1), &x0, &a0).unwrap().with_history(&hist, &hist_actions).unwrap();
    let (frames, acts) = r.condition();
    assert!(frames.select(1, 0).equal(&x0));
    assert!(frames.narrow(1, 1, 8).equal(&hist.narrow(1, 2, 8)));
    assert!(acts.narrow(0, 1, 8).equal(&hist_actions.narrow(0, 2, 8)));
    assert!(Rollout::new(&model, &vae, spec(8, 4, 1), &x0, &a0).unwrap().with_history(&hist, &hist_actions.narrow(0, 0, 9)).is_err());
}

#[test]
fn the_prefix_is_the_same_at_every_sampler_step() {
    let (model, vae) = parts(Kind::Float);
    let d = model.cfg.action.action_dim;
    let (x0, a0, actions) = inputs(d, 4);
    let s = spec(4, 4, 2);
    let p = s.condition_latents() as i64;
    let mut r = Rollout::new(&model, &vae, s, &x0, &a0).unwrap();
    let mut prefixes = Vec::new();
    r.next_chunk_traced(&actions, &mut |_, input, _| prefixes.push(input.narrow(2, 0, p).copy())).unwrap();
    assert_eq!(prefixes.len(), 3);
    assert!(prefixes.iter().all(|x| x.equal(&prefixes[0])));
    // The history part is noised (sigma_h > 0): it differs from the clean encode; x0 does not.
    let clean = tch::no_grad(|| vae.encode(&Tensor::stack(&(0..5).map(|_| x0.shallow_clone()).collect::<Vec<_>>(), 1).unsqueeze(0)).unwrap());
    assert!(prefixes[0].narrow(2, 0, 1).allclose(&clean.narrow(2, 0, 1), 1e-5, 1e-5, false), "x0 latent stays clean");
    assert!(!prefixes[0].narrow(2, 1, 1).allclose(&clean.narrow(2, 1, 1), 1e-3, 1e-3, false), "history latent is perturbed");

    let mut clean_run = Rollout::new(&model, &vae, RolloutSpec { history_sigma: None, ..spec(4, 4, 2) }, &x0, &a0).unwrap();
    let mut first = None;
    clean_run.next_chunk_traced(&actions, &mut |i, input, _| if i == 0 { first = Some(input.narrow(2, 0, p).copy()) }).unwrap();
    assert!(first.unwrap().allclose(&clean, 1e-5, 1e-5, false), "history noise switched off: the clean prefix");
}

#[test]
fn a_short_last_window_is_padded_with_its_last_action_and_trimmed() {
    let (model, vae) = parts(Kind::Float);
    let d = model.cfg.action.action_dim;
    let (_, _, actions) = inputs(d, 2);
    let short = roll(&model, &vae, spec(4, 4, 9), &actions);
    let padded = Tensor::cat(&[actions.shallow_clone(), actions.get(1).unsqueeze(0).expand([2, d], false)], 0);
    let full = roll(&model, &vae, spec(4, 4, 9), &padded);
    assert_eq!(short[0].0.size(), [3, 2, SIDE, SIDE]);
    assert!(short[0].0.allclose(&full[0].0.narrow(1, 0, 2), 1e-6, 1e-6, false));
    assert!(short[0].1.equal(&actions));
}

#[test]
fn rollouts_advanced_together_generate_what_each_generates_alone() {
    let (model, vae) = parts(Kind::Float);
    let d = model.cfg.action.action_dim;
    let (x0, a0, actions) = inputs(d, 8);
    let draw = |shape: &[i64], key: u64| keyed_rng::normal(shape, 13, key, Purpose::Augment).tanh();
    let (x1, a1) = (draw(&[3, SIDE, SIDE], 0), draw(&[d], 1));
    // Different seeds, first frames and window lengths (the second rollout's windows are short).
    let windows = [[actions.narrow(0, 0, 4), actions.narrow(0, 4, 4)], [actions.narrow(0, 1, 3), actions.narrow(0, 5, 2)]];
    let alone: Vec<Vec<Tensor>> = [(&x0, &a0, 5), (&x1, &a1, 6)]
        .iter()
        .zip(&windows)
        .map(|(&(x, a, seed), w)| {
            let mut r = Rollout::new(&model, &vae, spec(4, 4, seed), x, a).unwrap();
            w.iter().map(|w| r.next_chunk(w).unwrap().frames).collect()
        })
        .collect();
    let mut r0 = Rollout::new(&model, &vae, spec(4, 4, 5), &x0, &a0).unwrap();
    let mut r1 = Rollout::new(&model, &vae, spec(4, 4, 6), &x1, &a1).unwrap();
    for c in 0..2 {
        let chunks = Rollout::next_chunks(&mut [&mut r0, &mut r1], &[windows[0][c].shallow_clone(), windows[1][c].shallow_clone()]).unwrap();
        for (b, chunk) in chunks.iter().enumerate() {
            assert_eq!(chunk.index, c);
            assert!(chunk.actions.equal(&windows[b][c]));
            assert_eq!(chunk.frames.size(), alone[b][c].size());
            let diff = (&chunk.frames - &alone[b][c]).abs().max().double_value(&[]);
            assert!(diff < 1e-4, "rollout {b}, chunk {c}: batched and alone differ by {diff}");
        }
    }
    assert!(!alone[0][0].narrow(1, 0, 3).allclose(&alone[1][0], 1e-3, 1e-3, false), "the two rollouts differ, so the batch kept them apart");

    // Whole sequences of different lengths in lock step: the longer one goes on alone.
    let sequences = [actions.shallow_clone(), actions.narrow(0, 0, 5)];
    let mut s0 = Rollout::new(&model, &vae, spec(4, 4, 5), &x0, &a0).unwrap();
    let mut s1 = Rollout::new(&model, &vae, spec(4, 4, 6), &x1, &a1).unwrap();
    let mut together: Vec<Vec<Tensor>> = vec![Vec::new(), Vec::new()];
    Rollout::run_together(&mut [&mut s0, &mut s1], &sequences, &mut |i, c| {
        together[i].push(c.frames);
        Ok(())
    })
    .unwrap();
    for (b, (x, a, seed)) in [(&x0, &a0, 5), (&x1, &a1, 6)].into_iter().enumerate() {
        let mut r = Rollout::new(&model, &vae, spec(4, 4, seed), x, a).unwrap();
        let mut alone = Vec::new();
        r.run(&sequences[b], &mut |c| {
            alone.push(c.frames);
            Ok(())
        })
        .unwrap();
        assert_eq!(together[b].len(), alone.len(), "rollout {b}: chunks");
        for (t, a) in together[b].iter().zip(&alone) {
            assert_eq!(t.size(), a.size());
            assert!((t - a).abs().max().double_value(&[]) < 1e-4, "rollout {b}: run_together and run differ");
        }
    }
    assert_eq!(together.iter().map(Vec::len).collect::<Vec<_>>(), [2, 2], "8 actions and 5 in chunks of 4");

    // A batch holds one setting: another step count is refused, another seed is not.
    let mut other = Rollout::new(&model, &vae, RolloutSpec { steps: 2, ..spec(4, 4, 5) }, &x0, &a0).unwrap();
    let e = Rollout::next_chunks(&mut [&mut r0, &mut other], &[actions.narrow(0, 0, 4), actions.narrow(0, 0, 4)]).err().expect("mixed settings are refused");
    assert!(e.to_string().contains("differ from rollout 0"), "{e}");
    assert!(Rollout::next_chunks(&mut [&mut r0], &[]).is_err(), "one window per rollout");
}

/// Chunks queued for two batches before either is read back, and read back in the other order,
/// are what `next_chunk` gives each rollout; their phases are not timed apart. A chunk is read
/// back for as many rollouts as it was begun for.
#[test]
fn chunks_begun_for_two_batches_and_finished_in_turn_are_what_each_gets_alone() {
    let (model, vae) = parts(Kind::Float);
    let d = model.cfg.action.action_dim;
    let (x0, a0, actions) = inputs(d, 8);
    let alone: Vec<Vec<Tensor>> = [5, 6]
        .iter()
        .map(|&seed| {
            let mut r = Rollout::new(&model, &vae, spec(4, 4, seed), &x0, &a0).unwrap();
            (0..2).map(|c| r.next_chunk(&actions.narrow(0, 4 * c, 4)).unwrap().frames).collect()
        })
        .collect();
    let mut r0 = Rollout::new(&model, &vae, spec(4, 4, 5), &x0, &a0).unwrap();
    let mut r1 = Rollout::new(&model, &vae, spec(4, 4, 6), &x0, &a0).unwrap();
    for c in 0..2 {
        let window = [actions.narrow(0, 4 * c, 4)];
        let p0 = Rollout::begin_chunks(&[&r0], &window).unwrap();
        let p1 = Rollout::begin_chunks(&[&r1], &window).unwrap();
        for (b, (r, p)) in [(&mut r1, p1), (&mut r0, p0)].into_iter().enumerate() {
            let chunk = Rollout::finish_chunks(&mut [r], p).unwrap().remove(0);
            let want = &alone[1 - b][c as usize];
            assert_eq!(chunk.index, c as usize);
            assert!(chunk.encode_seconds.is_nan() && chunk.dit_seconds.is_nan() && chunk.decode_seconds.is_nan());
            let diff = (&chunk.frames - want).abs().max().double_value(&[]);
            assert!(diff < 1e-6, "rollout {}, chunk {c}: begun beside another batch, {diff} from alone", 1 - b);
        }
    }
    let p = Rollout::begin_chunks(&[&r0, &r1], &[actions.narrow(0, 0, 4), actions.narrow(0, 0, 4)]).unwrap();
    let e = Rollout::finish_chunks(&mut [&mut r0], p).err().expect("a chunk of two rollouts finished for one");
    assert!(e.to_string().contains("begun for 2 rollouts is finished for 1"), "{e}");
}

#[test]
fn bad_inputs_are_errors() {
    let (model, vae) = parts(Kind::Float);
    let d = model.cfg.action.action_dim;
    let (x0, a0, actions) = inputs(d, 4);
    assert!(Rollout::new(&model, &vae, spec(3, 4, 0), &x0, &a0).is_err(), "history not a multiple of 4");
    assert!(Rollout::new(&model, &vae, spec(4, 0, 0), &x0, &a0).is_err(), "no future");
    assert!(Rollout::new(&model, &vae, spec(4, 4, 0), &x0.narrow(1, 0, 16), &a0).is_err(), "height not a multiple of 32");
    assert!(Rollout::new(&model, &vae, spec(4, 4, 0), &x0, &a0.narrow(0, 0, d - 1)).is_err(), "action width");
    let mut r = Rollout::new(&model, &vae, spec(4, 4, 0), &x0, &a0).unwrap();
    assert!(r.next_chunk(&Tensor::cat(&[actions.shallow_clone(), actions.shallow_clone()], 0)).is_err(), "more than K actions");
    let nan = actions.copy();
    let _ = nan.get(0).get(0).fill_(f64::NAN);
    let e = r.next_chunk(&nan).err().expect("NaN actions are refused").to_string();
    assert!(e.contains("NaN"), "{e}");
}

#[test]
fn fp8_block_linears_roll_out_frames_close_to_the_exact_model() {
    let (exact, vae) = parts(Kind::Float);
    let (mut fp8, _) = parts(Kind::Float);
    let n = bwm_model::fp8::quantize_linears(&mut fp8, bwm_model::fp8::BLOCK_LINEARS, bwm_model::fp8::Fp8Scaling::Tensor).unwrap();
    assert_eq!(n, 10 * exact.dit.blocks.len(), "q, k, v, o of both attentions and the two FFN layers per block");
    let d = exact.cfg.action.action_dim;
    let (_, _, actions) = inputs(d, 4);
    let a = roll(&exact, &vae, spec(4, 4, 1), &actions);
    let b = roll(&fp8, &vae, spec(4, 4, 1), &actions);
    let diff = (&a[0].0 - &b[0].0).abs().mean(Kind::Float).double_value(&[]);
    assert!(diff > 0.0 && diff < 0.05, "FP8 vs exact mean abs pixel difference {diff}");
}

#[test]
fn bf16_model_rolls_out_finite_frames_close_to_f32() {
    let (m32, vae) = parts(Kind::Float);
    let (m16, _) = parts(Kind::BFloat16);
    let d = m32.cfg.action.action_dim;
    let (_, _, actions) = inputs(d, 4);
    let a = roll(&m32, &vae, spec(4, 4, 1), &actions);
    let b = roll(&m16, &vae, spec(4, 4, 1), &actions);
    assert_eq!(b[0].0.kind(), Kind::Float);
    assert!(bool::try_from(b[0].0.isfinite().all()).unwrap());
    let diff = (&a[0].0 - &b[0].0).abs().mean(Kind::Float).double_value(&[]);
    assert!(diff < 0.05, "bf16 vs f32 mean abs pixel difference {diff}");
}

#[test]
fn action_guidance_blends_the_conditional_and_null_velocities() {
    use bwm_model::sampler::{sample_chunk, Eager};
    use bwm_model::schedule::FlowSchedule;
    let (model, _) = parts(Kind::Float);
    let d = model.cfg.action.action_dim;
    let draw = |shape: &[i64], key: u64| keyed_rng::normal(shape, 12, key, Purpose::Augment);
    // Two samples, x0 + 1 history latent + 2 future latents of 4x4: 1 + 4*3 = 13 action frames.
    let latents = draw(&[2, 48, 4, 4, 4], 0);
    let t = Tensor::from_slice(&[500.0f32, 500.0]);
    let ft = bwm_model::bwm::frame_timesteps(&t, 4, 2);
    let (actions, other) = (draw(&[2, 13, d], 1).tanh(), draw(&[2, 13, d], 2).tanh());

    // The null condition: what a dropped sample trains on, independent of its actions.
    let v = |a: &Tensor, keep: Option<&Tensor>| tch::no_grad(|| model.forward_keeping(&latents, &ft, a, keep).unwrap());
    let all = Tensor::from_slice(&[1.0f32, 1.0]);
    let none = Tensor::from_slice(&[0.0f32, 0.0]);
    let mixed = Tensor::from_slice(&[1.0f32, 0.0]);
    let plain = tch::no_grad(|| model.forward(&latents, &ft, &actions).unwrap());
    assert!(v(&actions, Some(&all)).equal(&plain), "keeping every sample is the plain forward");
    assert!(v(&actions, None).equal(&plain));
    assert!(!v(&other, None).allclose(&plain, 1e-5, 1e-5, false), "the conditional velocity follows the actions");
    let null = v(&actions, Some(&none));
    assert!(v(&other, Some(&none)).allclose(&null, 1e-6, 1e-6, false), "the null velocity ignores the actions");
    assert!(!null.allclose(&plain, 1e-5, 1e-5, false));
    let m = v(&actions, Some(&mixed));
    assert!(m.get(0).allclose(&plain.get(0), 1e-5, 1e-5, false) && m.get(1).allclose(&null.get(1), 1e-5, 1e-5, false), "per sample");

    // One Euler step is affine in the velocity, so the guided chunks lie on a line in w; w = 0
    // samples from the null condition alone.
    let prefix = latents.narrow(2, 0, 2);
    let noise = draw(&[2, 48, 4, 4, 4], 3);
    let schedule = FlowSchedule::inference(1, 5.0);
    let chunk = |a: &Tensor, w: f64| tch::no_grad(|| sample_chunk(&mut Eager, &model, &prefix, &noise, a, &schedule, w, &mut |_, _, _| {}).unwrap());
    let (c0, c1, c2) = (chunk(&actions, 0.0), chunk(&actions, 1.0), chunk(&actions, 2.5));
    assert!((&c2 - &c1).allclose(&((&c1 - &c0) * 1.5), 1e-4, 1e-5, false), "v_null + w (v_cond - v_null)");
    assert!(!c2.allclose(&c1, 1e-5, 1e-5, false));
    assert!(chunk(&other, 0.0).allclose(&c0, 1e-5, 1e-5, false), "w = 0 ignores the actions");
    assert!(c1.narrow(2, 0, 2).equal(&prefix) && c2.narrow(2, 0, 2).equal(&prefix), "the prefix stays fixed");
    let e = sample_chunk(&mut Eager, &model, &prefix, &noise, &actions, &schedule, -1.0, &mut |_, _, _| {}).unwrap_err().to_string();
    assert!(e.contains("guidance"), "{e}");
    let e = RolloutSpec { guidance: f64::NAN, ..spec(4, 4, 0) }.validate().unwrap_err().to_string();
    assert!(e.contains("guidance"), "{e}");
}

/// A light decoder in place of the VAE's decoder: the same chunk shapes from the same latents,
/// other pixels; the VAE still encodes the history. A decoder for other latents, or a batch that
/// mixes decoders, is refused.
#[test]
fn a_light_decoder_decodes_the_chunks_in_place_of_the_vae() {
    use bwm_model::light_decoder::{LightDecoder, LightDecoderConfig};
    let (model, vae) = parts(Kind::Float);
    let d = model.cfg.action.action_dim;
    let (x0, a0, actions) = inputs(d, 6);
    let cfg = LightDecoderConfig { widths: [8, 8, 4, 4], blocks: 1, ..LightDecoderConfig::for_vae(&vae.cfg) };
    let (light, _) = LightDecoder::random(&cfg, Kind::Float, Device::Cpu, 5).unwrap();
    let mut full = Rollout::new(&model, &vae, spec(4, 4, 5), &x0, &a0).unwrap();
    let mut lit = Rollout::new(&model, &vae, spec(4, 4, 5), &x0, &a0).unwrap().with_light_decoder(&light).unwrap();
    for w in [actions.narrow(0, 0, 4), actions.narrow(0, 4, 2)] {
        let (a, b) = (full.next_chunk(&w).unwrap(), lit.next_chunk(&w).unwrap());
        assert_eq!(a.frames.size(), b.frames.size());
        assert!(b.frames.max().double_value(&[]) <= 1.0 && b.frames.min().double_value(&[]) >= -1.0);
        assert!(!a.frames.allclose(&b.frames, 1e-3, 1e-3, false), "the light decoder's pixels are its own");
    }
    let mut other = Rollout::new(&model, &vae, spec(4, 4, 6), &x0, &a0).unwrap();
    let mut lit2 = Rollout::new(&model, &vae, spec(4, 4, 5), &x0, &a0).unwrap().with_light_decoder(&light).unwrap();
    let e = Rollout::next_chunks(&mut [&mut lit2, &mut other], &[actions.narrow(0, 0, 4), actions.narrow(0, 0, 4)]).err().expect("mixed decoders are refused");
    assert!(e.to_string().contains("another decoder"), "{e}");
    let wrong = LightDecoderConfig { z_dim: cfg.z_dim + 1, ..cfg };
    let (wrong, _) = LightDecoder::random(&wrong, Kind::Float, Device::Cpu, 5).unwrap();
    assert!(Rollout::new(&model, &vae, spec(4, 4, 5), &x0, &a0).unwrap().with_light_decoder(&wrong).is_err());
}
