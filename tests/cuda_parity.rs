//! CUDA against CPU: the tiny model's forward with the same weights and inputs. Needs a GPU, so it
//! is ignored by default; the GPU machine runs it with `--ignored` (see docs/performance.md, "CUDA
//! parity and the DiT forward alone").

use bwm_model::{frame_timesteps, BwmModel, Layout, ModelConfig};
use tch::{Device, Kind, Tensor};

fn rel_err(a: &Tensor, b: &Tensor) -> f64 {
    let (a, b) = (a.to_device(Device::Cpu).to_kind(Kind::Double), b.to_device(Device::Cpu).to_kind(Kind::Double));
    (&a - &b).norm().double_value(&[]) / b.norm().double_value(&[])
}

#[test]
#[ignore = "needs a CUDA device; run on the GPU machine with --ignored"]
fn tiny_forward_on_cuda_matches_cpu() {
    if !bwm_testdir::need(bwm_testdir::Dep::Cuda, (!tch::Cuda::is_available()).then(|| "CUDA is not available to libtorch (is libtorch_cuda linked?)".to_string())) {
        return;
    }
    let cfg = ModelConfig::preset("tiny").unwrap();
    let cpu = BwmModel::random(&cfg, Kind::Float, Device::Cpu, 7).unwrap();
    let dir = bwm_testdir::TestDir::new("cuda-parity");
    let file = dir.join("tiny.safetensors");
    Tensor::write_safetensors(&cpu.store.named_parameters(), &file).unwrap();
    let gpu = BwmModel::load(&file, Layout::WanNative, &cfg, Kind::Float, Device::Cuda(0)).unwrap();
    let gpu_bf16 = BwmModel::load(&file, Layout::WanNative, &cfg, Kind::BFloat16, Device::Cuda(0)).unwrap();

    let (x, a) = bwm_model::vb::with_seed(3, || (Tensor::randn([2, 48, 5, 8, 12], (Kind::Float, Device::Cpu)), Tensor::rand([2, 17, 14], (Kind::Float, Device::Cpu)) * 2.0 - 1.0));
    let t = frame_timesteps(&Tensor::from_slice(&[900.0f32, 250.0]), 5, 3);
    let on = |d: Device| (x.to_device(d), t.to_device(d), a.to_device(d));
    let reference = tch::no_grad(|| cpu.forward(&x, &t, &a)).unwrap();
    let (xg, tg, ag) = on(Device::Cuda(0));
    let out = tch::no_grad(|| gpu.forward(&xg, &tg, &ag)).unwrap();
    let out16 = tch::no_grad(|| gpu_bf16.forward(&xg, &tg, &ag)).unwrap();
    let (e32, e16) = (rel_err(&out, &reference), rel_err(&out16, &reference));
    println!("cuda f32 vs cpu f32: rel err {e32:.3e}; cuda bf16 vs cpu f32: rel err {e16:.3e}");
    assert!(e32 < 1e-3, "cuda f32 rel err {e32}");
    assert!(e16 < 2e-2, "cuda bf16 rel err {e16}");
}
