//! Loss weights towards what moves in a clip, for the VAE's `motion` reconstruction loss and the
//! DiT's `objective.motion_weight`: in a robot's video the arm and what it touches are a small
//! part of a still scene, which dominates a plain mean.

use tch::{Kind, Tensor};

/// A sample whose mean spread change is under this is weighed nearly evenly: its noise is not
/// made into motion (an eighth of an 8-bit level in [-1, 1] pixels).
const MIN_MEAN_CHANGE: f64 = 1e-3;

/// Weights `[B, 1, F, H, W]` from `change` of that shape (how much each position changed from the
/// frame before): 1 + `weight` x the change spread to every position within `reach` of it (a max
/// over the window, so a still object beside what moved counts too), divided by the sample's mean
/// spread change (at least `MIN_MEAN_CHANGE`). A sample without change weighs everything 1; the
/// weights of one that changes average 1 + `weight`.
pub fn from_change(change: &Tensor, weight: f64, reach: i64) -> Tensor {
    tch::no_grad(|| {
        // The window's max in two passes, along the rows and then the columns.
        let k = 2 * reach + 1;
        let spread = change.max_pool3d([1, 1, k], [1, 1, 1], [0, 0, reach], [1, 1, 1], false).max_pool3d([1, k, 1], [1, 1, 1], [0, reach, 0], [1, 1, 1], false);
        let mean = spread.mean_dim(&[1i64, 2, 3, 4][..], true, Kind::Float).clamp_min(MIN_MEAN_CHANGE);
        spread / mean * weight + 1.0
    })
}

/// The mean change over the channels `[B, 1, F, H, W]` from `before` to `after`, both `[B, C, F, H, W]`.
pub fn change(before: &Tensor, after: &Tensor) -> Tensor {
    (after - before).abs().mean_dim(&[1i64][..], true, Kind::Float)
}

/// Per sample `[B]`: the mean of `values` `[B, C, F, H, W]` weighted by `w` `[B, 1, F, H, W]`
/// (shared by the channels: the means, not the sums, compare).
pub fn weighted_mean(values: &Tensor, w: &Tensor) -> Tensor {
    let dims = &[1i64, 2, 3, 4][..];
    (values * w).mean_dim(dims, false, Kind::Float) / w.mean_dim(dims, false, Kind::Float)
}
