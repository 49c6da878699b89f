//! Random draws keyed by (seed, global sample index, purpose), never by rank or by how many draws
//! came before, so 1 process and N processes with the same global batch draw the same numbers.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha12Rng;
use rand_distr::StandardNormal;
use tch::Tensor;

/// What a draw is for; each purpose has its own stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Purpose {
    Timestep = 1,
    Noise = 2,
    HistoryNoise = 3,
    Shuffle = 4,
    Validation = 5,
    Augment = 6,
    RolloutNoise = 7,
    RolloutHistoryNoise = 8,
    LoraInit = 9,
    ActionDropout = 10,
}

pub fn rng(seed: u64, index: u64, purpose: Purpose) -> ChaCha12Rng {
    let mut key = [0u8; 32];
    key[..8].copy_from_slice(&seed.to_le_bytes());
    key[8..16].copy_from_slice(&index.to_le_bytes());
    key[16..24].copy_from_slice(&(purpose as u64).to_le_bytes());
    ChaCha12Rng::from_seed(key)
}

/// Standard normal f32 tensor of `shape` on the CPU.
pub fn normal(shape: &[i64], seed: u64, index: u64, purpose: Purpose) -> Tensor {
    let n: i64 = shape.iter().product();
    let mut r = rng(seed, index, purpose);
    let values: Vec<f32> = (0..n).map(|_| r.sample(StandardNormal)).collect();
    Tensor::from_slice(&values).view(shape)
}

/// Uniform f32 tensor in [-bound, bound) of `shape` on the CPU.
pub fn uniform_tensor(shape: &[i64], bound: f64, seed: u64, index: u64, purpose: Purpose) -> Tensor {
    let n: i64 = shape.iter().product();
    let mut r = rng(seed, index, purpose);
    let values: Vec<f32> = (0..n).map(|_| ((r.gen::<f64>() * 2.0 - 1.0) * bound) as f32).collect();
    Tensor::from_slice(&values).view(shape)
}

/// Uniform in [0, 1).
pub fn uniform(seed: u64, index: u64, purpose: Purpose) -> f64 {
    rng(seed, index, purpose).gen::<f64>()
}

/// One standard normal number.
pub fn standard_normal(seed: u64, index: u64, purpose: Purpose) -> f64 {
    rng(seed, index, purpose).sample(StandardNormal)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_depend_only_on_the_key() {
        let a = normal(&[3, 4], 7, 11, Purpose::Noise);
        let b = normal(&[3, 4], 7, 11, Purpose::Noise);
        assert!(a.equal(&b));
        assert!(!a.equal(&normal(&[3, 4], 7, 12, Purpose::Noise)));
        assert!(!a.equal(&normal(&[3, 4], 7, 11, Purpose::HistoryNoise)));
        assert!(!a.equal(&normal(&[3, 4], 8, 11, Purpose::Noise)));
        let u = uniform(1, 2, Purpose::Timestep);
        assert!((0.0..1.0).contains(&u));
        assert_eq!(u, uniform(1, 2, Purpose::Timestep));
    }
}
