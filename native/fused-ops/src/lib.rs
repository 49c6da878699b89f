//! The DiT's element-wise steps that libtorch runs as several passes over the tokens, each as one
//! pass each way, as autograd functions (libtorch's autograd takes no custom backward from tch, so
//! they are C++: src/ops.cpp; the passes are this crate's: CUDA kernels compiled with NVRTC at first
//! use, src/kernel.rs):
//! - [`rotate`], Wan's rotary embedding. The tensor path (`x.to_kind(f32)`, a complex product, the
//!   cast back) makes three passes over q and k each way and holds them in fp32 in between; here
//!   each pair (x0, x1) is read once in its own dtype, rotated in fp32 and written once, and the
//!   backward pass rotates the incoming gradient back. On the CPU the same arithmetic is a loop.
//! - [`frame_addcmul`], a + b * c with c (and a, for the modulation's shift) one value per frame
//!   and channel: the modulation and the gates. libtorch broadcasts c through its unvectorized
//!   kernel, and its backward makes the product g * b in bf16, then sums it in another pass; here
//!   the backward reads g and b once, writes b's gradient and sums c's (and a's) in fp32. On the
//!   CPU the same arithmetic is libtorch's tensors in fp32.
//! - [`fp8_quantize_pass`], the quantization of `bwm-fp8-autograd`'s FP8 linear (which calls it
//!   through a function pointer): a tensor scaled by its largest magnitude into float8, row-major
//!   and transposed, in one pass with the scale computed where the values are. libtorch casts to
//!   float8 and copies float8 tensors with its one-element-per-thread kernels and needs several
//!   small kernels for the scale (docs/performance.md at abaed68, "FP8 training of the block
//!   linears"). On the CPU the same
//!   arithmetic is a loop.

mod kernel;

pub use kernel::load_module;

use std::ffi::{c_char, c_int, c_void, CStr};
use std::sync::Once;

use anyhow::{bail, Result};
use tch::{Device, Kind, Tensor};
use torch_sys::C_tensor;

type RopePass = extern "C" fn(*mut c_void, c_int, c_int, *const c_void, *const c_void, *mut c_void, i64, i64, i64, i64, c_int, *mut c_char, usize) -> c_int;
type FramePass = extern "C" fn(*mut c_void, c_int, c_int, *const c_void, c_int, *const c_void, *const c_void, *mut c_void, *const c_void, *const c_void, *const c_void, *mut c_void, *mut f32, *mut f32, i64, i64, i64, i64, *mut c_char, usize) -> c_int;

extern "C" {
    fn bwm_fused_ops_set_passes(rope: RopePass, frame: FramePass);
    fn bwm_fused_rope(x: *const C_tensor, rotations: *const C_tensor, out: *mut *mut C_tensor) -> *const c_char;
    fn bwm_fused_frame_addcmul(a: *const C_tensor, b: *const C_tensor, c: *const C_tensor, out: *mut *mut C_tensor) -> *const c_char;
}

/// Whether the operations run on `device`: always on the CPU; on a CUDA device once its kernels
/// compiled (NVRTC must be on the library path).
pub fn available(device: Device) -> bool {
    match device {
        Device::Cpu => true,
        Device::Cuda(index) => kernel::Kernels::for_device(index).is_ok(),
        _ => false,
    }
}

/// Calls a C++ entry point that writes a new tensor or returns an error message.
fn call(what: &str, f: impl FnOnce(*mut *mut C_tensor) -> *const c_char) -> Result<Tensor> {
    static SET: Once = Once::new();
    // SAFETY: hands the C++ side functions of the signatures it declares.
    SET.call_once(|| unsafe { bwm_fused_ops_set_passes(rope_pass, frame_pass) });
    let mut out: *mut C_tensor = std::ptr::null_mut();
    let err = f(&mut out);
    if !err.is_null() {
        bail!("{what}: {}", unsafe { CStr::from_ptr(err) }.to_string_lossy());
    }
    // SAFETY: on success the C++ side wrote a new at::Tensor*, which this takes ownership of.
    Ok(unsafe { Tensor::from_ptr(out) })
}

/// x [B, L, heads, head_dim] (f32 or bf16) with each channel pair (2j, 2j+1) of token l rotated
/// by `rotations` [L, 1, head_dim / 2] (complex64) as (x0 + i x1) r, computed in fp32 and returned
/// in x's dtype; differentiable in x.
pub fn rotate(x: &Tensor, rotations: &Tensor) -> Result<Tensor> {
    // SAFETY: both pointers are live tch tensors (at::Tensor*).
    call("rotary embedding", |out| unsafe { bwm_fused_rope(x.as_ptr(), rotations.as_ptr(), out) })
}

/// a + b * c computed in fp32 and returned in their dtype (f32 or bf16, the same for all three):
/// b [B, F, P, D] (F frames of P tokens), c [B, F, 1, D], a either b's shape (a gate's residual)
/// or c's (the modulation's shift); D a multiple of 8. Differentiable in a, b and c.
pub fn frame_addcmul(a: &Tensor, b: &Tensor, c: &Tensor) -> Result<Tensor> {
    // SAFETY: the pointers are live tch tensors (at::Tensor*).
    call("frame multiply-add", |out| unsafe { bwm_fused_frame_addcmul(a.as_ptr(), b.as_ptr(), c.as_ptr(), out) })
}

/// Whether [`frame_addcmul`] takes these operands (shapes, one dtype of f32 or bf16, one device
/// where [`available`]).
pub fn frame_addcmul_takes(a: &Tensor, b: &Tensor, c: &Tensor) -> bool {
    let s = b.size();
    let kind = b.kind();
    s.len() == 4
        && s[3] % 8 == 0
        && c.size() == [s[0], s[1], 1, s[3]]
        && (a.size() == s || a.size() == c.size())
        && matches!(kind, Kind::Float | Kind::BFloat16)
        && a.kind() == kind
        && c.kind() == kind
        && a.device() == b.device()
        && c.device() == b.device()
        && available(b.device())
}

/// The shape of one pass: `tokens` rows (B * L) of `heads` heads of `pairs` pairs; token t's
/// rotations are row t % `len` of the table.
#[derive(Clone, Copy)]
struct Shape {
    tokens: i64,
    len: i64,
    heads: i64,
    pairs: i64,
}

/// The passes' dtype code: 0 f32, 1 bf16 (whether bf16).
fn is_bf16(dtype: c_int) -> Result<bool> {
    match dtype {
        0 => Ok(false),
        1 => Ok(true),
        other => bail!("unknown dtype code {other} (0: f32, 1: bf16)"),
    }
}

/// Writes `e` into the C++ side's error buffer of err_len + 1 zeroed bytes; returns 1.
fn report(e: anyhow::Error, err: *mut c_char, err_len: usize) -> c_int {
    let message = format!("{e:#}");
    let n = message.len().min(err_len);
    // SAFETY: `err` holds err_len + 1 zeroed bytes (src/ops.cpp); at most err_len are written.
    unsafe { std::ptr::copy_nonoverlapping(message.as_ptr(), err as *mut u8, n) };
    1
}

/// The rotation's pass the C++ side calls (`RopePass` in src/ops.cpp), which has checked the
/// shapes, dtypes, contiguity, alignment and devices.
extern "C" fn rope_pass(stream: *mut c_void, device: c_int, dtype: c_int, x: *const c_void, rotations: *const c_void, out: *mut c_void, tokens: i64, len: i64, heads: i64, pairs: i64, inverse: c_int, err: *mut c_char, err_len: usize) -> c_int {
    let shape = Shape { tokens, len, heads, pairs };
    let bf16 = match is_bf16(dtype) {
        Ok(bf16) => bf16,
        Err(e) => return report(e, err, err_len),
    };
    if device < 0 {
        cpu_rotate(bf16, x, rotations, out, shape, inverse != 0);
        return 0;
    }
    match kernel::Kernels::for_device(device as usize).and_then(|k| k.rotate(stream, bf16, x as u64, rotations as u64, out as u64, shape, inverse != 0)) {
        Ok(()) => 0,
        Err(e) => report(e, err, err_len),
    }
}

/// The frame operation's passes on CUDA (`FramePass` in src/ops.cpp: the forward when `a` is
/// set, else the backward), checked there as the rotation's are.
#[allow(clippy::too_many_arguments)]
extern "C" fn frame_pass(
    stream: *mut c_void,
    device: c_int,
    dtype: c_int,
    a: *const c_void,
    a_per_frame: c_int,
    b: *const c_void,
    c: *const c_void,
    out: *mut c_void,
    g: *const c_void,
    gb: *const c_void,
    gc: *const c_void,
    db: *mut c_void,
    partial_c: *mut f32,
    partial_a: *mut f32,
    frames: i64,
    rows: i64,
    dim: i64,
    rows_per_sum: i64,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    let shape = FrameShape { frames, rows, dim, rows_per_sum };
    let result = if device < 0 {
        Err(anyhow::anyhow!("the frame operation's CPU pass is libtorch's"))
    } else {
        is_bf16(dtype).and_then(|bf16| {
            let k = kernel::Kernels::for_device(device as usize)?;
            if !a.is_null() {
                k.frame_forward(stream, bf16, [a as u64, b as u64, c as u64, out as u64], a_per_frame != 0, shape)
            } else {
                k.frame_backward(stream, bf16, [g as u64, gb as u64, gc as u64, db as u64, partial_c as u64, partial_a as u64], shape)
            }
        })
    };
    match result {
        Ok(()) => 0,
        Err(e) => report(e, err, err_len),
    }
}

/// An FP8 quantization's shape: t [rows, cols], its transpose [cols, padded_rows].
#[derive(Clone, Copy)]
struct Fp8Shape {
    rows: i64,
    cols: i64,
    padded_rows: i64,
}

impl Fp8Shape {
    /// The f32 scratch the column sums take on CUDA: one row of `cols` per tile of 32 rows of the
    /// transposed layout (the vectorized kernel's tiles of 64 rows take half), at least one.
    pub fn sum_partials(&self) -> i64 {
        ((self.padded_rows + 31) / 32).max(1) * self.cols
    }

    /// Whether the pass can take whole groups of values (the kernel's vectorized form): rows of
    /// whole groups of 8 values, transposed rows of whole groups of 16 bytes, and `buffers` ([t,
    /// partials, q, qt, scale] addresses, 0 where not written) aligned to them.
    fn vectorizes(&self, buffers: [u64; 5]) -> bool {
        let [t, _, q, qt, _] = buffers;
        self.cols % 8 == 0 && t % 16 == 0 && q % 8 == 0 && (qt == 0 || (self.padded_rows % 16 == 0 && qt % 16 == 0))
    }
}

/// The float8 formats of the quantization.
const E4M3: c_int = 0;
const E5M2: c_int = 1;

/// [`fp8_quantize_pass`]'s signature, as fp8-autograd's C++ side declares it (`QuantizePass`).
pub type Fp8QuantizePass = extern "C" fn(
    *mut c_void,
    c_int,
    c_int,
    c_int,
    f64,
    *const c_void,
    *mut f32,
    i64,
    *mut u8,
    *mut u8,
    *mut f32,
    *mut f32,
    i64,
    *mut c_void,
    i64,
    i64,
    i64,
    *mut c_char,
    usize,
) -> c_int;
const _: Fp8QuantizePass = fp8_quantize_pass;

/// The FP8 quantization pass (`QuantizePass` in `bwm-fp8-autograd`'s src/fp8_linear.cpp, which
/// checks the shapes, dtypes, contiguity and devices): t [rows, cols] of dtype `dtype` (0: f32, 1:
/// bf16) at `t`; writes float8(t * m) (`format` 0: e4m3fn, 1: e5m2) row-major to `q` and
/// transposed, zero-padded to `padded_rows` columns, to `qt` (either null: not written), and 1 / m
/// to the f32 at `scale`, with m = headroom_max / max(amax, 1e-12) rounded to t's dtype, amax t's
/// largest magnitude (NaN if t holds one). On CUDA `partials` is scratch for `n_partials` f32 on
/// t's device (1 to 65535; the largest magnitude's partial maxima, one per block of the first of
/// two kernels); the CPU does not use it. Where `sums` is set, t's column sums (added in fp32,
/// written in t's dtype) go to its `cols` values (a linear layer's bias gradient, read in the same
/// pass); on CUDA they take `sum_partials`, scratch for `n_sum_partials` f32, at least
/// max(1, ceil(padded_rows / 32)) * cols (`Fp8Shape::sum_partials`). The arithmetic is libtorch's
/// tensor path's (the infinity norm; a reciprocal times the headroom in fp32, clamped to f32's
/// range; each product rounded to t's dtype, then to float8, nearest even). `device` -1: the CPU
/// (stream null).
#[allow(clippy::too_many_arguments)]
pub extern "C" fn fp8_quantize_pass(
    stream: *mut c_void,
    device: c_int,
    dtype: c_int,
    format: c_int,
    headroom_max: f64,
    t: *const c_void,
    partials: *mut f32,
    n_partials: i64,
    q: *mut u8,
    qt: *mut u8,
    scale: *mut f32,
    sum_partials: *mut f32,
    n_sum_partials: i64,
    sums: *mut c_void,
    rows: i64,
    cols: i64,
    padded_rows: i64,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    let shape = Fp8Shape { rows, cols, padded_rows };
    let e5m2 = match format {
        E4M3 => false,
        E5M2 => true,
        other => return report(anyhow::anyhow!("unknown float8 format {other}"), err, err_len),
    };
    let bf16 = match is_bf16(dtype) {
        Ok(bf16) => bf16,
        Err(e) => return report(e, err, err_len),
    };
    if device < 0 {
        cpu_fp8_quantize(bf16, e5m2, headroom_max as f32, t, q, qt, scale, sums, shape);
        return 0;
    }
    if !sums.is_null() && n_sum_partials < shape.sum_partials() {
        let e = anyhow::anyhow!("column sums of {rows}x{cols} (padded to {padded_rows} rows) need {} f32 of scratch, got {n_sum_partials}", shape.sum_partials());
        return report(e, err, err_len);
    }
    let buffers = [t as u64, partials as u64, q as u64, qt as u64, scale as u64];
    let sums = (!sums.is_null()).then_some((sum_partials as u64, sums as u64));
    match kernel::Kernels::for_device(device as usize).and_then(|k| k.fp8_quantize(stream, bf16, e5m2, buffers, sums, n_partials, headroom_max, shape)) {
        Ok(()) => 0,
        Err(e) => report(e, err, err_len),
    }
}

/// fp32 -> float8 e4m3fn, nearest even (NaN from 480 up: the format has no infinity), as the
/// kernel and c10 convert.
fn to_e4m3(x: f32) -> u8 {
    let u = x.to_bits();
    let sign = ((u >> 24) & 0x80) as u8;
    let u = u & 0x7fff_ffff;
    if u > 0x7f80_0000 || u >= 0x43f0_0000 {
        return sign | 0x7f;
    }
    if u < 0x3c80_0000 {
        return sign | (f32::from_bits(u) * 512.0).round_ties_even() as u8;
    }
    sign | (((u + 0x7_ffff + ((u >> 20) & 1)) >> 20) - (120 << 3)) as u8
}

/// fp32 -> float8 e5m2, nearest even (infinity from 65536 up), as the kernel and c10 convert.
fn to_e5m2(x: f32) -> u8 {
    let u = x.to_bits();
    let sign = ((u >> 24) & 0x80) as u8;
    let u = u & 0x7fff_ffff;
    if u > 0x7f80_0000 {
        return sign | 0x7f;
    }
    if u >= 0x4780_0000 {
        return sign | 0x7c;
    }
    if u < 0x3880_0000 {
        return sign | (f32::from_bits(u) * 65536.0).round_ties_even() as u8;
    }
    sign | (((u + 0xf_ffff + ((u >> 21) & 1)) >> 21) - (112 << 2)) as u8
}

/// The quantization kernel's arithmetic on the CPU, element by element; the column sums row by
/// row (the kernels add in another order).
#[allow(clippy::too_many_arguments)]
fn cpu_fp8_quantize(bf16: bool, e5m2: bool, headroom_max: f32, t: *const c_void, q: *mut u8, qt: *mut u8, scale: *mut f32, sums: *mut c_void, s: Fp8Shape) {
    let (rows, cols, padded) = (s.rows as usize, s.cols as usize, s.padded_rows as usize);
    // SAFETY: the C++ side passes t of rows * cols elements of t's dtype; q of rows * cols bytes
    // and qt of cols * padded_rows bytes where not null; one f32 at scale; cols values of t's
    // dtype at sums where not null.
    let load = |p: *const c_void, i: usize| -> f32 { unsafe { if bf16 { from_bf16(*(p as *const u16).add(i)) } else { *(p as *const f32).add(i) } } };
    let round = |x: f32| if bf16 { from_bf16(to_bf16(x)) } else { x };
    let a = (0..rows * cols).map(|i| load(t, i).abs()).fold(0.0f32, |a, v| if a > v || a.is_nan() { a } else { v });
    let a = if a < 1e-12 { 1e-12 } else { a };
    let m = (1.0 / a) * headroom_max;
    let m = round(if m > f32::MAX { f32::MAX } else { m });
    unsafe { *scale = 1.0 / m };
    if !sums.is_null() {
        let mut acc = vec![0.0f32; cols];
        for r in 0..rows {
            for (c, a) in acc.iter_mut().enumerate() {
                *a += load(t, r * cols + c);
            }
        }
        for (c, sum) in acc.into_iter().enumerate() {
            unsafe {
                if bf16 {
                    *(sums as *mut u16).add(c) = to_bf16(sum);
                } else {
                    *(sums as *mut f32).add(c) = sum;
                }
            }
        }
    }
    let cast = if e5m2 { to_e5m2 } else { to_e4m3 };
    for r in 0..padded {
        for c in 0..cols {
            let v = if r < rows { cast(round(load(t, r * cols + c) * m)) } else { 0 };
            unsafe {
                if r < rows && !q.is_null() {
                    *q.add(r * cols + c) = v;
                }
                if !qt.is_null() {
                    *qt.add(c * padded + r) = v;
                }
            }
        }
    }
}

/// The frame operation's shape: `frames` (B * F) of `rows` tokens (P) of `dim` channels (D); the
/// backward sums each frame's rows in runs of `rows_per_sum`.
#[derive(Clone, Copy)]
struct FrameShape {
    frames: i64,
    rows: i64,
    dim: i64,
    rows_per_sum: i64,
}

fn from_bf16(h: u16) -> f32 {
    f32::from_bits((h as u32) << 16)
}

/// fp32 -> bf16 rounding to nearest even, as the kernel and c10::BFloat16 round.
fn to_bf16(x: f32) -> u16 {
    let u = x.to_bits();
    if u & 0x7fff_ffff > 0x7f80_0000 {
        return ((u >> 16) | 0x40) as u16;
    }
    ((u + 0x7fff + ((u >> 16) & 1)) >> 16) as u16
}

/// The rotation kernel's arithmetic on the CPU, pair by pair.
fn cpu_rotate(bf16: bool, x: *const c_void, rotations: *const c_void, out: *mut c_void, s: Shape, inverse: bool) {
    let n = (s.tokens * s.heads * s.pairs) as usize;
    // SAFETY: the C++ side passes contiguous buffers of 2n elements of x's dtype (x, out) and
    // len * pairs complex64 values (the rotations), which outlive this call.
    let r = unsafe { std::slice::from_raw_parts(rotations as *const [f32; 2], (s.len * s.pairs) as usize) };
    let load = |i: usize| -> [f32; 2] {
        unsafe {
            if bf16 {
                let p = x as *const u16;
                [from_bf16(*p.add(2 * i)), from_bf16(*p.add(2 * i + 1))]
            } else {
                let p = x as *const f32;
                [*p.add(2 * i), *p.add(2 * i + 1)]
            }
        }
    };
    for i in 0..n {
        let pair = i as i64 % s.pairs;
        let token = i as i64 / (s.pairs * s.heads);
        let [c, mut sn] = r[((token % s.len) * s.pairs + pair) as usize];
        if inverse {
            sn = -sn;
        }
        let [a, b] = load(i);
        let (y0, y1) = (a * c - b * sn, a * sn + b * c);
        unsafe {
            if bf16 {
                let p = out as *mut u16;
                *p.add(2 * i) = to_bf16(y0);
                *p.add(2 * i + 1) = to_bf16(y1);
            } else {
                let p = out as *mut f32;
                *p.add(2 * i) = y0;
                *p.add(2 * i + 1) = y1;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Kind;

    /// Quantized through the pass (on t's device): the float8 bytes row-major and transposed
    /// ([cols, padded rows]) and the scale.
    fn pass_quantize(t: &Tensor, e5m2: bool, pad: bool) -> (Vec<u8>, Vec<u8>, f32) {
        let (q, qt, scale, _) = pass_quantize_in(t, e5m2, pad, PARTIALS, false);
        (q, qt, scale)
    }

    /// As fp8-autograd's src/fp8_linear.cpp calls it.
    const PARTIALS: i64 = 256;

    /// [`pass_quantize`] with the largest magnitude reduced over `partials` blocks on CUDA, and
    /// with t's column sums where `sums` (then also returned).
    fn pass_quantize_in(t: &Tensor, e5m2: bool, pad: bool, partials: i64, sums: bool) -> (Vec<u8>, Vec<u8>, f32, Vec<f32>) {
        let t = t.contiguous();
        let (rows, cols) = (t.size()[0], t.size()[1]);
        let padded = if pad { (rows + 15) / 16 * 16 } else { rows };
        let device = t.device();
        let n_partials = partials;
        let partials = Tensor::full([partials], f64::NAN, (Kind::Float, device));
        let q = Tensor::zeros([rows, cols], (Kind::Uint8, device));
        let qt = Tensor::full([cols, padded], 0x55, (Kind::Uint8, device));
        let scale = Tensor::zeros([], (Kind::Float, device));
        let n_sum_partials = Fp8Shape { rows, cols, padded_rows: padded }.sum_partials();
        let sum_partials = Tensor::full([n_sum_partials], f64::NAN, (Kind::Float, device));
        let column_sums = Tensor::full([cols], f64::NAN, (t.kind(), device));
        let (stream, index) = match device {
            // The kernels run on the default stream here: libtorch's current one in a test thread.
            Device::Cuda(i) => (std::ptr::null_mut(), i as c_int),
            _ => (std::ptr::null_mut(), -1),
        };
        let fmax = if e5m2 { 57344.0 } else { 448.0 };
        let mut err = vec![0 as c_char; 513];
        let failed = fp8_quantize_pass(
            stream,
            index,
            (t.kind() == Kind::BFloat16) as c_int,
            if e5m2 { E5M2 } else { E4M3 },
            fmax * (1.0 - 1.0 / 64.0),
            t.data_ptr(),
            partials.data_ptr() as *mut f32,
            n_partials,
            q.data_ptr() as *mut u8,
            qt.data_ptr() as *mut u8,
            scale.data_ptr() as *mut f32,
            sum_partials.data_ptr() as *mut f32,
            n_sum_partials,
            if sums { column_sums.data_ptr() } else { std::ptr::null_mut() },
            rows,
            cols,
            padded,
            err.as_mut_ptr(),
            512,
        );
        assert_eq!(failed, 0, "{}", unsafe { CStr::from_ptr(err.as_ptr()) }.to_string_lossy());
        let bytes = |x: &Tensor| Vec::<u8>::try_from(x.to_device(Device::Cpu).view([-1])).unwrap();
        let sums = if sums { Vec::<f32>::try_from(column_sums.to_device(Device::Cpu).to_kind(Kind::Float)).unwrap() } else { Vec::new() };
        (bytes(&q), bytes(&qt), scale.to_device(Device::Cpu).double_value(&[]) as f32, sums)
    }

    /// Column sums against libtorch's (added in fp32), each within fp32's rounding of its
    /// column's sum of magnitudes and, for bf16, one rounding to bf16 of the sum.
    fn check_sums(t: &Tensor, sums: &[f32], what: &str) {
        let rounding = if t.kind() == Kind::BFloat16 { 1.0 / 256.0 } else { 0.0 };
        let t = t.to_device(Device::Cpu).to_kind(Kind::Float);
        let want = Vec::<f32>::try_from(t.sum_dim_intlist(0, false, Kind::Float)).unwrap();
        let bound = Vec::<f32>::try_from(t.abs().sum_dim_intlist(0, false, Kind::Float)).unwrap();
        assert_eq!(sums.len(), want.len(), "{what}: {} column sums for {} columns", sums.len(), want.len());
        for (c, ((got, want), bound)) in sums.iter().zip(&want).zip(&bound).enumerate() {
            let tolerance = 1e-5 * bound + rounding * want.abs();
            assert!((got - want).abs() <= tolerance, "{what}: column {c} sums to {got}, libtorch {want} (magnitudes {bound})");
        }
    }

    /// fp8-autograd's libtorch path before the pass: the infinity norm, a reciprocal times the
    /// headroom in fp32, the multiplier in t's dtype, the product in t's dtype cast to float8.
    fn tensor_quantize(t: &Tensor, e5m2: bool) -> (Vec<u8>, f32) {
        let fmax = if e5m2 { 57344.0 } else { 448.0 };
        let amax = t.abs().max().to_kind(Kind::Float);
        let m = (amax.clamp_min(1e-12).reciprocal() * (fmax * (1.0 - 1.0 / 64.0))).clamp_max(f32::MAX as f64).to_kind(t.kind());
        let q = (t * &m).to_kind(if e5m2 { Kind::Float8e5m2 } else { Kind::Float8e4m3fn });
        let bytes = Vec::<u8>::try_from(q.view_dtype(Kind::Uint8).to_device(Device::Cpu).contiguous().view([-1])).unwrap();
        (bytes, m.to_kind(Kind::Float).reciprocal().to_device(Device::Cpu).double_value(&[]) as f32)
    }

    /// Values spread over many binades (and exact zeros), so that the cast meets subnormals,
    /// ties and the format's top.
    fn spread(rows: i64, cols: i64, kind: Kind, device: Device, seed: i64) -> Tensor {
        tch::manual_seed(seed);
        let x = Tensor::randn([rows, cols], (Kind::Float, Device::Cpu)) * (Tensor::randn([rows, cols], (Kind::Float, Device::Cpu)) * 4.0).exp2();
        let x = x.where_self(&Tensor::rand([rows, cols], (Kind::Float, Device::Cpu)).gt(0.05), &Tensor::zeros([], (Kind::Float, Device::Cpu)));
        x.to_kind(kind).to_device(device)
    }

    /// The quantization's loop on the CPU against libtorch's tensor path, byte for byte, and its
    /// transpose against the row-major values with zero padding rows.
    fn check_quantize(device: Device) {
        for kind in [Kind::Float, Kind::BFloat16] {
            for e5m2 in [false, true] {
                for (rows, cols, pad) in [(37, 48, true), (64, 16, false), (5, 3, true), (37, 48, false), (100, 72, true)] {
                    let t = spread(rows, cols, kind, device, rows + cols);
                    let (q, qt, scale) = pass_quantize(&t, e5m2, pad);
                    // The bias gradient's column sums, read in the same pass, change none of its bytes.
                    let (q2, qt2, scale2, sums) = pass_quantize_in(&t, e5m2, pad, PARTIALS, true);
                    assert!(q2 == q && qt2 == qt && scale2.to_bits() == scale.to_bits(), "{kind:?} e5m2 {e5m2} {rows}x{cols}: the column sums changed the cast");
                    check_sums(&t, &sums, &format!("{kind:?} {rows}x{cols} on {device:?}"));
                    let (want, want_scale) = tensor_quantize(&t, e5m2);
                    let differ = q.iter().zip(&want).filter(|(a, b)| a != b).count();
                    assert_eq!(differ, 0, "{kind:?} e5m2 {e5m2} {rows}x{cols} on {device:?}: {differ} of {} values differ from libtorch's cast", q.len());
                    assert_eq!(scale.to_bits(), want_scale.to_bits(), "{kind:?} e5m2 {e5m2}: scale {scale} against {want_scale}");
                    let padded = qt.len() / cols as usize;
                    for c in 0..cols as usize {
                        for r in 0..padded {
                            let v = if r < rows as usize { q[r * cols as usize + c] } else { 0 };
                            assert_eq!(qt[c * padded + r], v, "{kind:?} e5m2 {e5m2}: transposed ({c}, {r})");
                        }
                    }
                }
            }
        }
        // An all-zero tensor: the largest magnitude clamped, every value zero.
        let (q, _, scale) = pass_quantize(&Tensor::zeros([4, 16], (Kind::BFloat16, device)), false, true);
        assert!(q.iter().all(|&b| b == 0) && scale > 0.0 && scale.is_finite());
        // An empty tensor: nothing to write but the scale, and zero sums.
        let (q, qt, scale, sums) = pass_quantize_in(&Tensor::zeros([0, 16], (Kind::BFloat16, device)), false, true, PARTIALS, true);
        assert!(q.is_empty() && qt.is_empty() && scale > 0.0 && scale.is_finite());
        assert!(sums.len() == 16 && sums.iter().all(|&s| s == 0.0), "{sums:?}");
        // A NaN anywhere: the largest magnitude NaN, as libtorch's norm gives it, so every value NaN.
        for kind in [Kind::Float, Kind::BFloat16] {
            let t = spread(40, 48, kind, device, 3);
            let _ = t.get(31).get(5).fill_(f64::NAN);
            let (q, qt, scale) = pass_quantize(&t, false, true);
            assert!(scale.is_nan() && q.iter().chain(&qt[..40]).all(|&b| b & 0x7f == 0x7f), "{kind:?}: a NaN did not spread");
        }
    }

    #[test]
    fn unknown_codes_are_errors() {
        let t = Tensor::zeros([4, 16], (Kind::Float, Device::Cpu));
        let (q, scale) = (Tensor::zeros([4, 16], (Kind::Uint8, Device::Cpu)), Tensor::zeros([], (Kind::Float, Device::Cpu)));
        let null = std::ptr::null_mut();
        for (dtype, format, want) in [(2, E4M3, "unknown dtype code 2"), (0, 7, "unknown float8 format 7")] {
            let mut err = vec![0 as c_char; 513];
            let failed = fp8_quantize_pass(null, -1, dtype, format, 441.0, t.data_ptr(), null as *mut f32, 0, q.data_ptr() as *mut u8, null as *mut u8,
                                           scale.data_ptr() as *mut f32, null as *mut f32, 0, null, 4, 16, 4, err.as_mut_ptr(), 512);
            let message = unsafe { CStr::from_ptr(err.as_ptr()) }.to_string_lossy().into_owned();
            assert!(failed != 0 && message.contains(want), "{message}");
        }
        let mut err = vec![0 as c_char; 513];
        let out = Tensor::zeros([1, 2, 1, 4], (Kind::Float, Device::Cpu));
        let r = Tensor::zeros([2, 1, 2], (Kind::ComplexFloat, Device::Cpu));
        assert_ne!(rope_pass(null, -1, 3, out.data_ptr(), r.data_ptr(), out.data_ptr(), 2, 2, 1, 2, 0, err.as_mut_ptr(), 512), 0);
        assert!(unsafe { CStr::from_ptr(err.as_ptr()) }.to_string_lossy().contains("unknown dtype code 3"));
    }

    #[test]
    fn whole_groups_of_aligned_values_take_the_vectorized_kernel() {
        let shape = |rows, cols, padded_rows| Fp8Shape { rows, cols, padded_rows };
        let aligned = [256, 512, 1024, 2048, 4096];
        assert!(shape(6300, 14336, 6304).vectorizes(aligned));
        assert!(shape(37, 48, 37).vectorizes([256, 512, 1024, 0, 4096]), "no transpose: its rows may be any number");
        assert!(!shape(37, 48, 37).vectorizes(aligned), "transposed rows of 37 bytes");
        assert!(!shape(5, 3, 16).vectorizes(aligned), "rows of 3 values");
        assert!(!shape(64, 16, 64).vectorizes([264, 512, 1024, 2048, 4096]), "t off 16 bytes");
        assert!(!shape(64, 16, 64).vectorizes([256, 512, 1028, 2048, 4096]), "q off 8 bytes");
        assert!(!shape(64, 16, 64).vectorizes([256, 512, 1024, 2056, 4096]), "qt off 16 bytes");
    }

    #[test]
    fn the_fp8_quantization_casts_as_libtorch_and_transposes_on_the_cpu() {
        check_quantize(Device::Cpu);
        // Every e4m3 value round-trips through the conversion (NaN as NaN).
        for b in 0u8..=255 {
            let x = Tensor::from_slice(&[b]).view_dtype(Kind::Float8e4m3fn).to_kind(Kind::Float).double_value(&[0]) as f32;
            assert!(to_e4m3(x) == b || (x.is_nan() && to_e4m3(x) & 0x7f == 0x7f), "e4m3 byte {b:#x} ({x}) -> {:#x}", to_e4m3(x));
            let y = Tensor::from_slice(&[b]).view_dtype(Kind::Float8e5m2).to_kind(Kind::Float).double_value(&[0]) as f32;
            assert!(to_e5m2(y) == b || (y.is_nan() && to_e5m2(y) & 0x7f > 0x7c), "e5m2 byte {b:#x} ({y}) -> {:#x}", to_e5m2(y));
        }
    }

    /// The tensor path this replaces (`bwm_model::rope::Rope::apply` before it): pairs as complex
    /// numbers in fp32, times the rotations, cast back.
    fn tensor_path(x: &Tensor, rotations: &Tensor) -> Tensor {
        let s = x.size();
        let pairs = x.to_kind(Kind::Float).view([s[0], s[1], s[2], s[3] / 2, 2]).view_as_complex();
        (pairs * rotations).view_as_real().view(s.as_slice()).to_kind(x.kind())
    }

    fn rotations(len: i64, pairs: i64, device: Device) -> Tensor {
        let angle = Tensor::rand([len, 1, pairs], (Kind::Float, device)) * 6.3;
        Tensor::complex(&angle.cos(), &angle.sin())
    }

    /// Forward and gradient against the tensor path for shapes of 1 and 4 pairs per thread,
    /// returning the largest differences (forward, gradient) relative to the values' largest.
    fn compare(device: Device, kind: Kind, shape: [i64; 4]) -> (f64, f64) {
        tch::manual_seed(7);
        let [b, l, n, d] = shape;
        let r = rotations(l, d / 2, device);
        let x0 = Tensor::randn(shape, (Kind::Float, device)).to_kind(kind);
        let up = Tensor::randn(shape, (Kind::Float, device));
        let run = |f: &dyn Fn(&Tensor) -> Tensor| {
            let x = x0.copy().set_requires_grad(true);
            let y = f(&x);
            (y.to_kind(Kind::Float) * &up).sum(Kind::Float).backward();
            (y.detach().to_kind(Kind::Float), x.grad().to_kind(Kind::Float))
        };
        let (y, g) = run(&|x| {
            let y = rotate(x, &r).unwrap();
            assert_eq!((y.size(), y.kind(), y.device()), (vec![b, l, n, d], kind, device));
            y
        });
        let (y0, g0) = run(&|x| tensor_path(x, &r));
        let rel = |a: &Tensor, b: &Tensor| (a - b).abs().max().double_value(&[]) / b.abs().max().double_value(&[]);
        (rel(&y, &y0), rel(&g, &g0))
    }

    #[test]
    fn rotates_and_rotates_back_as_the_tensor_path_on_the_cpu() {
        // head_dim 16: 8 pairs, four at a time on CUDA; head_dim 6: 3 pairs, one at a time.
        for shape in [[2, 5, 3, 16], [1, 7, 2, 6]] {
            let (y, g) = compare(Device::Cpu, Kind::Float, shape);
            assert!(y < 1e-6 && g < 1e-6, "{shape:?} f32: forward {y:e}, gradient {g:e}");
            // bf16 out: both round the same fp32 value once.
            let (y, g) = compare(Device::Cpu, Kind::BFloat16, shape);
            assert!(y < 1e-2 && g < 1e-2, "{shape:?} bf16: forward {y:e}, gradient {g:e}");
        }
    }

    #[test]
    fn the_rotation_is_undone_by_its_backward() {
        // A rotation's gradient is the inverse rotation: y's gradient rotated back is x's.
        let r = rotations(4, 4, Device::Cpu);
        let x = Tensor::randn([1, 4, 2, 8], (Kind::Float, Device::Cpu)).set_requires_grad(true);
        let y = rotate(&x, &r).unwrap();
        (&y * y.detach()).sum(Kind::Float).backward();
        let back = x.grad();
        assert!((&back - x.detach()).abs().max().double_value(&[]) < 1e-6, "rotating back did not give x");
    }

    #[test]
    fn bad_shapes_are_errors() {
        let r = rotations(4, 4, Device::Cpu);
        let err = |x: Tensor, r: &Tensor| format!("{:#}", rotate(&x, r).unwrap_err());
        let x = |s: [i64; 4]| Tensor::zeros(s, (Kind::Float, Device::Cpu));
        assert!(err(x([1, 5, 2, 8]), &r).contains("values for 5 tokens"), "{}", err(x([1, 5, 2, 8]), &r));
        assert!(err(x([1, 4, 2, 7]), &r).contains("must be even"));
        assert!(err(Tensor::zeros([4, 8], (Kind::Float, Device::Cpu)), &r).contains("[B, L, heads, head_dim]"));
        assert!(err(x([1, 4, 2, 8]).to_kind(Kind::Half), &r).contains("f32 or bf16"));
        assert!(err(x([1, 4, 2, 8]), &r.real()).contains("complex64"));
    }

    /// On a GPU (`bash scripts/gpu/unit.sh fused`): the kernels against the tensor path, and bit
    /// for bit against the CPU loop (both without multiply-add contraction).
    #[test]
    #[ignore = "needs a CUDA device"]
    fn the_kernels_rotate_as_the_tensor_path_and_the_cpu_loop_on_cuda() {
        let device = Device::Cuda(0);
        assert!(available(device), "{:#}", kernel::Kernels::for_device(0).err().map(|e| e.to_string()).unwrap_or_default());
        for shape in [[2, 5, 3, 16], [1, 7, 2, 6], [1, 300, 24, 128]] {
            let (y, g) = compare(device, Kind::Float, shape);
            assert!(y < 1e-6 && g < 1e-6, "{shape:?} f32: forward {y:e}, gradient {g:e}");
            let (y, g) = compare(device, Kind::BFloat16, shape);
            assert!(y < 1e-2 && g < 1e-2, "{shape:?} bf16: forward {y:e}, gradient {g:e}");
            for kind in [Kind::Float, Kind::BFloat16] {
                let [_, l, _, d] = shape;
                let r = rotations(l, d / 2, device);
                let x = Tensor::randn(shape, (Kind::Float, device)).to_kind(kind);
                let on_gpu = rotate(&x, &r).unwrap().to_device(Device::Cpu);
                let on_cpu = rotate(&x.to_device(Device::Cpu), &r.to_device(Device::Cpu)).unwrap();
                assert!(on_gpu.equal(&on_cpu), "{shape:?} {kind:?}: the kernel and the CPU loop differ");
            }
        }
        // Offset by one element: the C++ side copies to an aligned buffer first.
        let r = rotations(3, 4, device);
        let base = Tensor::randn([1 + 3 * 8], (Kind::BFloat16, device));
        let x = base.narrow(0, 1, 24).view([1, 3, 1, 8]);
        let diff = (rotate(&x, &r).unwrap().to_kind(Kind::Float) - tensor_path(&x, &r).to_kind(Kind::Float)).abs().max().double_value(&[]);
        assert!(diff < 2e-2, "misaligned input: {diff}");
    }

    /// Forward, and the gradients of a, b and c, of `frame_addcmul` and of libtorch's addcmul on
    /// the same operands (a whole or per frame); returns the largest differences relative to the
    /// largest values of each.
    fn frame_differences(device: Device, kind: Kind, shape: [i64; 4], a_whole: bool, against_cpu: bool) -> [f64; 4] {
        tch::manual_seed(11);
        let [b, f, _, d] = shape;
        let per_frame = [b, f, 1, d];
        let init = |s: &[i64]| Tensor::randn(s, (Kind::Float, device)).to_kind(kind);
        let (a0, b0, c0) = (init(if a_whole { &shape } else { &per_frame }), init(&shape), init(&per_frame));
        let up = Tensor::randn(shape, (Kind::Float, device));
        let run = |on: Device, f: &dyn Fn(&Tensor, &Tensor, &Tensor) -> Tensor| {
            let leaf = |t: &Tensor| t.to_device(on).copy().set_requires_grad(true);
            let (a, b, c) = (leaf(&a0), leaf(&b0), leaf(&c0));
            let y = f(&a, &b, &c);
            (y.to_kind(Kind::Float) * up.to_device(on)).sum(Kind::Float).backward();
            [y.detach(), a.grad(), b.grad(), c.grad()].map(|t| t.to_device(Device::Cpu).to_kind(Kind::Float))
        };
        let got = run(device, &|a, b, c| frame_addcmul(a, b, c).unwrap());
        let want = if against_cpu { run(Device::Cpu, &|a, b, c| frame_addcmul(a, b, c).unwrap()) } else { run(device, &|a, b, c| a.addcmul(b, c)) };
        std::array::from_fn(|i| (&got[i] - &want[i]).abs().max().double_value(&[]) / want[i].abs().max().double_value(&[]))
    }

    #[test]
    fn the_frame_multiply_add_and_its_gradients_follow_addcmul_on_the_cpu() {
        for a_whole in [true, false] {
            let e = frame_differences(Device::Cpu, Kind::Float, [2, 3, 5, 16], a_whole, false);
            assert!(e.iter().all(|&x| x < 1e-5), "f32, a whole {a_whole}: {e:?}");
            // bf16: libtorch's backward rounds g * b to bf16 before summing; here it is summed in fp32.
            let e = frame_differences(Device::Cpu, Kind::BFloat16, [2, 3, 5, 16], a_whole, false);
            assert!(e.iter().all(|&x| x < 2e-2), "bf16, a whole {a_whole}: {e:?}");
        }
    }

    #[test]
    fn frame_operands_are_checked() {
        let z = |s: &[i64], k: Kind| Tensor::zeros(s, (k, Device::Cpu));
        let f = Kind::Float;
        let err = |a: Tensor, b: Tensor, c: Tensor| {
            assert!(!frame_addcmul_takes(&a, &b, &c));
            format!("{:#}", frame_addcmul(&a, &b, &c).unwrap_err())
        };
        assert!(err(z(&[1, 2, 3, 8], f), z(&[1, 2, 3, 8], f), z(&[1, 2, 3, 8], f)).contains("c must be [1, 2, 1, 8]"));
        assert!(err(z(&[1, 2, 2, 8], f), z(&[1, 2, 3, 8], f), z(&[1, 2, 1, 8], f)).contains("a must be"));
        assert!(err(z(&[1, 2, 3, 6], f), z(&[1, 2, 3, 6], f), z(&[1, 2, 1, 6], f)).contains("multiple of 8"));
        assert!(err(z(&[1, 2, 3, 8], f), z(&[1, 2, 3, 8], Kind::BFloat16), z(&[1, 2, 1, 8], f)).contains("share a dtype"));
        assert!(frame_addcmul_takes(&z(&[1, 2, 1, 8], f), &z(&[1, 2, 3, 8], f), &z(&[1, 2, 1, 8], f)));
    }

    /// On a GPU (`bash scripts/gpu/unit.sh fused`): the frame kernels against the CPU arithmetic
    /// (the forward and b's gradient bit for bit; the sums within their order's rounding) and
    /// against libtorch's addcmul, at the 5B's width and at a width under one warp of threads.
    /// The quantization kernel against libtorch's tensor path on the GPU and against its own
    /// transpose, as on the CPU (shapes that take the vectorized kernel and shapes that do not),
    /// and at the 5B's widest shape (vectorized) against the CPU loop.
    #[test]
    #[ignore = "needs a CUDA device"]
    fn the_fp8_quantization_kernel_casts_as_libtorch_and_the_cpu_loop_on_cuda() {
        let device = Device::Cuda(0);
        assert!(available(device));
        check_quantize(device);
        for e5m2 in [false, true] {
            let t = spread(6300, 14336, Kind::BFloat16, device, 7);
            let cpu = pass_quantize_in(&t.to_device(Device::Cpu), e5m2, true, PARTIALS, true);
            for partials in [PARTIALS, 1, 7] {
                let gpu = pass_quantize_in(&t, e5m2, true, partials, true);
                assert!(gpu.0 == cpu.0 && gpu.1 == cpu.1 && gpu.2 == cpu.2, "e5m2 {e5m2}, {partials} partial maxima: the kernels and the CPU loop differ at the 5B's FFN width");
                check_sums(&t, &gpu.3, &format!("e5m2 {e5m2}, {partials} partial maxima, 6300x14336 on CUDA"));
            }
        }
    }

    #[test]
    #[ignore = "needs a CUDA device"]
    fn the_frame_kernels_follow_the_cpu_arithmetic_and_addcmul_on_cuda() {
        let device = Device::Cuda(0);
        assert!(available(device));
        for (shape, kind) in [([2, 3, 37, 16], Kind::Float), ([2, 3, 37, 16], Kind::BFloat16), ([1, 21, 300, 3072], Kind::BFloat16)] {
            for a_whole in [true, false] {
                let e = frame_differences(device, kind, shape, a_whole, true);
                assert!(e[0] == 0.0 && e[2] == 0.0, "{shape:?} {kind:?}, a whole {a_whole}: forward / b's gradient not bit for bit: {e:?}");
                let bound = if kind == Kind::Float { 1e-5 } else { 1e-2 };
                assert!(e[1] < bound && e[3] < bound, "{shape:?} {kind:?}, a whole {a_whole}: sums {e:?}");
                let e = frame_differences(device, kind, shape, a_whole, false);
                let bound = if kind == Kind::Float { 1e-5 } else { 2e-2 };
                assert!(e.iter().all(|&x| x < bound), "{shape:?} {kind:?}, a whole {a_whole}, against addcmul: {e:?}");
            }
        }
    }
}
