//! The CUDA kernels, compiled with NVRTC once per device and launched on the stream
//! the C++ side reports as libtorch's current one (so that they also run inside a CUDA graph's
//! capture).

use std::ffi::c_void;
use std::sync::{Arc, Mutex, OnceLock};

use anyhow::{anyhow, ensure, Context, Result};
use cudarc::driver::{CudaContext, CudaFunction, CudaModule};

use crate::{Fp8Shape, FrameShape, Shape};

/// One block per token. Where a head's pairs are a multiple of 4, each thread reads and writes 4
/// pairs at once (16 bytes of bf16); else one pair.
const SOURCE: &str = r#"
// fp32 -> bf16, rounding to nearest even (as c10::BFloat16 and __float2bfloat16_rn).
__device__ unsigned short to_bf16(float x) {
  unsigned int u = __float_as_uint(x);
  if ((u & 0x7fffffffu) > 0x7f800000u) return (unsigned short)((u >> 16) | 0x40u);
  return (unsigned short)((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
}

__device__ __forceinline__ void load(const float* x, long long g, int n, float* v) {
  if (n == 4) {
    float4 a = ((const float4*)x)[2 * g], b = ((const float4*)x)[2 * g + 1];
    v[0] = a.x; v[1] = a.y; v[2] = a.z; v[3] = a.w; v[4] = b.x; v[5] = b.y; v[6] = b.z; v[7] = b.w;
  } else {
    float2 a = ((const float2*)x)[g];
    v[0] = a.x; v[1] = a.y;
  }
}

__device__ __forceinline__ void load(const unsigned short* x, long long g, int n, float* v) {
  if (n == 4) {
    uint4 u = ((const uint4*)x)[g];
    unsigned int w[4] = {u.x, u.y, u.z, u.w};
    for (int h = 0; h < 4; h++) {
      v[2 * h] = __uint_as_float(w[h] << 16);
      v[2 * h + 1] = __uint_as_float(w[h] & 0xffff0000u);
    }
  } else {
    unsigned int u = ((const unsigned int*)x)[g];
    v[0] = __uint_as_float(u << 16);
    v[1] = __uint_as_float(u & 0xffff0000u);
  }
}

__device__ __forceinline__ void store(float* out, long long g, int n, const float* v) {
  if (n == 4) {
    ((float4*)out)[2 * g] = make_float4(v[0], v[1], v[2], v[3]);
    ((float4*)out)[2 * g + 1] = make_float4(v[4], v[5], v[6], v[7]);
  } else {
    ((float2*)out)[g] = make_float2(v[0], v[1]);
  }
}

__device__ __forceinline__ void store(unsigned short* out, long long g, int n, const float* v) {
  unsigned int w[4];
  for (int h = 0; h < n; h++) w[h] = (unsigned int)to_bf16(v[2 * h]) | ((unsigned int)to_bf16(v[2 * h + 1]) << 16);
  if (n == 4) {
    ((uint4*)out)[g] = make_uint4(w[0], w[1], w[2], w[3]);
  } else {
    ((unsigned int*)out)[g] = w[0];
  }
}

// Token blockIdx.x's groups of N pairs: `groups` per token, `per_head` per head; its rotations are
// row (token % len) of `rot`, pairs = per_head * N wide. sign -1 rotates back.
template <typename T, int N>
__device__ void rotate(const T* x, const float2* rot, T* out, int len, int groups, int per_head, float sign) {
  long long token = blockIdx.x;
  const float2* r = rot + (long long)(token % len) * per_head * N;
  for (int j = threadIdx.x; j < groups; j += blockDim.x) {
    long long g = token * groups + j;
    const float2* rj = r + (j % per_head) * N;
    float v[2 * N];
    load(x, g, N, v);
    for (int h = 0; h < N; h++) {
      float c = rj[h].x, s = sign * rj[h].y, a = v[2 * h], b = v[2 * h + 1];
      v[2 * h] = a * c - b * s;
      v[2 * h + 1] = a * s + b * c;
    }
    store(out, g, N, v);
  }
}

// Every parameter is 64 bits wide (the launcher passes an array of u64).
#define ARGS(T) const T* x, const float2* rot, T* out, long long len, long long groups, long long per_head, long long inverse
#define CALL(T, N) rotate<T, N>(x, rot, out, (int)len, (int)groups, (int)per_head, inverse ? -1.0f : 1.0f)
extern "C" __global__ void rope_f32_4(ARGS(float)) { CALL(float, 4); }
extern "C" __global__ void rope_f32_1(ARGS(float)) { CALL(float, 1); }
extern "C" __global__ void rope_bf16_4(ARGS(unsigned short)) { CALL(unsigned short, 4); }
extern "C" __global__ void rope_bf16_1(ARGS(unsigned short)) { CALL(unsigned short, 1); }

// a + b * c over `frames` frames of `rows` rows of 8 * dim8 channels, 8 channels per thread; c (and
// a where a_per_frame) hold one row per frame.
template <typename T>
__device__ void frame_forward(const T* a, long long a_per_frame, const T* b, const T* c, T* out, long long frames, long long rows, long long dim8) {
  long long groups = frames * rows * dim8;
  for (long long i = blockIdx.x * (long long)blockDim.x + threadIdx.x; i < groups; i += (long long)gridDim.x * blockDim.x) {
    long long row = i / dim8, d8 = i - row * dim8;
    long long ci = (row / rows) * dim8 + d8;
    float av[8], bv[8], cv[8];
    load(a, a_per_frame ? ci : i, 4, av);
    load(b, i, 4, bv);
    load(c, ci, 4, cv);
    for (int k = 0; k < 8; k++) av[k] = av[k] + bv[k] * cv[k];
    store(out, i, 4, av);
  }
}

// The backward of a + b * c from the output's gradient g: db = g * c, and the sums of g * b and of
// g (where pa is not null) over each run of `run` rows of a frame (block (frame, run)) in fp32,
// [frames, runs, 8 * dim8]; the caller sums the runs.
template <typename T>
__device__ void frame_backward(const T* g, const T* b, const T* c, T* db, float* pc, float* pa, long long rows, long long dim8, long long run) {
  long long frame = blockIdx.x;
  long long r0 = blockIdx.y * run, r1 = min(rows, r0 + run);
  for (long long d8 = threadIdx.x; d8 < dim8; d8 += blockDim.x) {
    float cv[8], sc[8], sa[8];
    load(c, frame * dim8 + d8, 4, cv);
    for (int k = 0; k < 8; k++) { sc[k] = 0.0f; sa[k] = 0.0f; }
    for (long long r = r0; r < r1; r++) {
      long long i = (frame * rows + r) * dim8 + d8;
      float gv[8], bv[8], out[8];
      load(g, i, 4, gv);
      load(b, i, 4, bv);
      for (int k = 0; k < 8; k++) {
        out[k] = gv[k] * cv[k];
        sc[k] = sc[k] + gv[k] * bv[k];
        sa[k] = sa[k] + gv[k];
      }
      store(db, i, 4, out);
    }
    long long p = ((frame * gridDim.y + blockIdx.y) * dim8 + d8) * 8;
    for (int k = 0; k < 8; k++) pc[p + k] = sc[k];
    if (pa) for (int k = 0; k < 8; k++) pa[p + k] = sa[k];
  }
}

#define FWD(T) const T* a, long long a_per_frame, const T* b, const T* c, T* out, long long frames, long long rows, long long dim8
#define BWD(T) const T* g, const T* b, const T* c, T* db, float* pc, float* pa, long long rows, long long dim8, long long run
extern "C" __global__ void frame_forward_f32(FWD(float)) { frame_forward<float>(a, a_per_frame, b, c, out, frames, rows, dim8); }
extern "C" __global__ void frame_forward_bf16(FWD(unsigned short)) { frame_forward<unsigned short>(a, a_per_frame, b, c, out, frames, rows, dim8); }
extern "C" __global__ void frame_backward_f32(BWD(float)) { frame_backward<float>(g, b, c, db, pc, pa, rows, dim8, run); }
extern "C" __global__ void frame_backward_bf16(BWD(unsigned short)) { frame_backward<unsigned short>(g, b, c, db, pc, pa, rows, dim8, run); }

// fp32 -> float8, rounding to nearest even, as c10's conversions do for finite values: e4m3fn
// (no infinities; past its range NaN) and e5m2 (past its range infinity). By hand: the cvt
// instructions need sm_89, and the module is compiled for any device.
__device__ unsigned char to_e4m3(float x) {
  unsigned int u = __float_as_uint(x);
  unsigned char sign = (unsigned char)((u >> 24) & 0x80u);
  u &= 0x7fffffffu;
  if (u > 0x7f800000u || u >= 0x43f00000u) return sign | 0x7fu;  // NaN, or at least 480
  if (u < 0x3c800000u) return sign | (unsigned char)rintf(__uint_as_float(u) * 512.0f);  // under 2^-6: steps of 2^-9
  return sign | (unsigned char)(((u + 0x7ffffu + ((u >> 20) & 1u)) >> 20) - (120u << 3));
}

__device__ unsigned char to_e5m2(float x) {
  unsigned int u = __float_as_uint(x);
  unsigned char sign = (unsigned char)((u >> 24) & 0x80u);
  u &= 0x7fffffffu;
  if (u > 0x7f800000u) return sign | 0x7fu;
  if (u >= 0x47800000u) return sign | 0x7cu;  // at least 65536: infinity
  if (u < 0x38800000u) return sign | (unsigned char)rintf(__uint_as_float(u) * 65536.0f);  // under 2^-14: steps of 2^-16
  return sign | (unsigned char)(((u + 0xfffffu + ((u >> 21) & 1u)) >> 21) - (112u << 2));
}

__device__ __forceinline__ float value(float x) { return x; }
__device__ __forceinline__ float value(unsigned short x) { return __uint_as_float((unsigned int)x << 16); }
__device__ __forceinline__ float rounded(float x, const float*) { return x; }
__device__ __forceinline__ float rounded(float x, const unsigned short*) {
#if __CUDA_ARCH__ >= 800
  unsigned short h;  // the instruction rounds as to_bf16 (NaN aside: it gives the canonical one)
  asm("cvt.rn.bf16.f32 %0, %1;" : "=h"(h) : "f"(x));
  return __uint_as_float((unsigned int)h << 16);
#else
  return __uint_as_float((unsigned int)to_bf16(x) << 16);
#endif
}

// float8 bytes of p: Ada's and Hopper's conversion instruction where the device has it (the
// values reaching it lie within the format, where it rounds as the loops above; it saturates
// where they give NaN), else the loops. to_fp8x2: lo's byte, then hi's.
template <bool E5M2>
__device__ __forceinline__ unsigned short to_fp8x2(float lo, float hi) {
#if __CUDA_ARCH__ >= 890
  unsigned short d;
  if (E5M2) asm("cvt.rn.satfinite.e5m2x2.f32 %0, %1, %2;" : "=h"(d) : "f"(hi), "f"(lo));
  else asm("cvt.rn.satfinite.e4m3x2.f32 %0, %1, %2;" : "=h"(d) : "f"(hi), "f"(lo));
  return d;
#else
  return E5M2 ? (unsigned short)(to_e5m2(lo) | (to_e5m2(hi) << 8)) : (unsigned short)(to_e4m3(lo) | (to_e4m3(hi) << 8));
#endif
}

template <bool E5M2>
__device__ __forceinline__ unsigned char to_fp8(float p) { return (unsigned char)(to_fp8x2<E5M2>(p, 0.0f) & 0xffu); }

// The larger of two magnitudes, NaN if either is (as libtorch's maximum and norms propagate it).
__device__ __forceinline__ float nan_max(float a, float b) { return (a > b || a != a) ? a : b; }

// The largest magnitude of t's n values, in `partials`: one per block of 1024 threads (gridDim.x
// of them), which the quantization kernels reduce. vec: n a multiple of 8 and t 16-byte aligned,
// 8 values per load, four loads in flight per thread (one leaves most of the bandwidth unused).
template <typename T>
__device__ void fp8_amax(const T* __restrict__ t, long long n, float* __restrict__ partials, bool vec) {
  __shared__ float warps[32];
  float a = 0.0f;
  const long long stride = (long long)gridDim.x * blockDim.x, first = (long long)blockIdx.x * blockDim.x + threadIdx.x;
  if (vec) {
    const long long groups = n / 8;
    long long g = first;
    for (; g + 3 * stride < groups; g += 4 * stride) {
      float v[4][8];
      for (int j = 0; j < 4; j++) load(t, g + j * stride, 4, v[j]);
      for (int j = 0; j < 4; j++)
        for (int k = 0; k < 8; k++) a = nan_max(a, fabsf(v[j][k]));
    }
    for (; g < groups; g += stride) {
      float v[8];
      load(t, g, 4, v);
      for (int k = 0; k < 8; k++) a = nan_max(a, fabsf(v[k]));
    }
  } else {
    for (long long i = first; i < n; i += stride) a = nan_max(a, fabsf(value(t[i])));
  }
  for (int o = 16; o > 0; o >>= 1) a = nan_max(a, __shfl_xor_sync(0xffffffffu, a, o));
  if ((threadIdx.x & 31) == 0) warps[threadIdx.x >> 5] = a;
  __syncthreads();
  if (threadIdx.x < 32) {
    a = threadIdx.x < (blockDim.x >> 5) ? warps[threadIdx.x] : 0.0f;
    for (int o = 16; o > 0; o >>= 1) a = nan_max(a, __shfl_xor_sync(0xffffffffu, a, o));
    if (threadIdx.x == 0) partials[blockIdx.x] = a;
  }
}

// q = float8(t * m) of t [rows, cols] and, where qt is set, its transpose [cols, padded_rows] (the
// rows past `rows` zero), with m = headroom_max / max(amax, 1e-12) in t's dtype and scale = 1 / m,
// amax the largest of the n partial maxima fp8_amax left: the arithmetic of fp8-autograd's
// libtorch path (the infinity norm; a reciprocal times the headroom, each in fp32; the product
// rounded to t's dtype before the cast). Every thread of the block must call it (it syncs them);
// the kernels issue their loads of t before it, so that they wait on one latency, not two.
template <typename T>
__device__ __forceinline__ float multiplier(const T*, const float* __restrict__ partials, long long n, float headroom_max, float* scale) {
  __shared__ float amax;
  if (threadIdx.x < 32 && threadIdx.y == 0) {
    float a = 0.0f;
#pragma unroll 8
    for (long long i = threadIdx.x; i < n; i += 32) a = nan_max(a, partials[i]);
    for (int o = 16; o > 0; o >>= 1) a = nan_max(a, __shfl_xor_sync(0xffffffffu, a, o));
    if (threadIdx.x == 0) amax = a;
  }
  __syncthreads();
  float a = amax < 1e-12f ? 1e-12f : amax;
  float m = (1.0f / a) * headroom_max;
  m = m > 3.40282346638528859812e+38f ? 3.40282346638528859812e+38f : m;
  m = rounded(m, (const T*)nullptr);
  if (scale && blockIdx.x == 0 && blockIdx.y == 0 && threadIdx.x == 0 && threadIdx.y == 0) scale[0] = 1.0f / m;
  return m;
}

// A 32 x 32 tile per block of 32 x 8 threads; blockIdx.x walks the rows, blockIdx.y the columns.
// Where sum_partials is set, each block also writes its tile's column sums of t (fp32, t's own
// values) to row blockIdx.x of sum_partials [row tiles, cols], which column_sums adds up.
template <typename T, bool E5M2>
__device__ void fp8_quantize(const T* t, const float* partials, long long n_partials, float headroom_max, unsigned char* q, unsigned char* qt,
                             float* scale, float* sum_partials, long long rows, long long cols, long long padded_rows) {
  __shared__ unsigned char tile[32][33];
  const long long r0 = (long long)blockIdx.x * 32, c0 = (long long)blockIdx.y * 32;
  float x[4];
  for (int k = 0; k < 4; k++) {
    long long r = r0 + threadIdx.y + 8 * k, c = c0 + threadIdx.x;
    x[k] = r < rows && c < cols ? value(t[r * cols + c]) : 0.0f;
  }
  __shared__ float part[8][32];  // each row of threads' column sums, added up after multiplier's barrier
  if (sum_partials) part[threadIdx.y][threadIdx.x] = ((x[0] + x[1]) + x[2]) + x[3];
  float m = multiplier(t, partials, n_partials, headroom_max, scale);
  if (sum_partials && threadIdx.y == 0 && c0 + threadIdx.x < cols) {
    float s = part[0][threadIdx.x];
    for (int w = 1; w < 8; w++) s += part[w][threadIdx.x];
    sum_partials[(long long)blockIdx.x * cols + c0 + threadIdx.x] = s;
  }
  for (int k = 0; k < 4; k++) {
    long long r = r0 + threadIdx.y + 8 * k, c = c0 + threadIdx.x;
    unsigned char v = 0;
    if (r < rows && c < cols) {
      v = to_fp8<E5M2>(rounded(x[k] * m, t));
      if (q) q[r * cols + c] = v;
    }
    tile[threadIdx.y + 8 * k][threadIdx.x] = v;
  }
  if (!qt) return;  // the same for the whole block
  __syncthreads();
  for (int k = 0; k < 32; k += 8) {
    long long c = c0 + threadIdx.y + k, r = r0 + threadIdx.x;
    if (c < cols && r < padded_rows) qt[c * padded_rows + r] = tile[threadIdx.x][threadIdx.y + k];
  }
}

// The same pass where every row is whole groups of 8 values (cols % 8 == 0), the transpose's
// rows whole groups of 16 (padded_rows % 16 == 0) and the buffers aligned to them (t and qt to 16
// bytes, q to 8): a 64 x 64 tile per block of 256 threads. Each thread reads two groups of 8
// values with one load each before converting any (the one-value-per-thread pass above leaves
// most of the memory's bandwidth unused), writes each group's 8 float8 bytes with one store, and
// one 16-byte row segment of the transpose. The blocks take the tiles in row-major order from
// the last: t's end, which fp8_amax read last and L2 may still hold (no gain measured on an H200).
template <typename T, bool E5M2>
__device__ void fp8_quantize_vec(const T* __restrict__ t, const float* __restrict__ partials, long long n_partials, float headroom_max,
                                 unsigned char* __restrict__ q, unsigned char* __restrict__ qt, float* __restrict__ scale,
                                 float* __restrict__ sum_partials, long long rows, long long cols, long long padded_rows) {
  __shared__ __align__(16) unsigned char tile[64][68];  // written a word at a time
  const int tid = threadIdx.x;
  const long long tiles = (long long)gridDim.x * gridDim.y, nth = tiles - 1 - ((long long)blockIdx.y * gridDim.x + blockIdx.x);
  const long long row_tile = nth / gridDim.y, r0 = row_tile * 64, c0 = (nth % gridDim.y) * 64;
  float v[2][8];
  bool in[2];
  for (int i = 0; i < 2; i++) {  // group (tid + 256 i): row / 8 of the tile, 8 values from column 8 * (group % 8)
    int g = tid + 256 * i;
    long long r = r0 + (g >> 3), c = c0 + (g & 7) * 8;
    in[i] = r < rows && c < cols;
    if (in[i]) load(t, (r * cols + c) >> 3, 4, v[i]);
  }
  __shared__ float part[8][64];  // each warp's column sums, added up after multiplier's barrier
  if (sum_partials) {  // the same for the whole block: a warp's lanes l, l + 8, l + 16, l + 24 share columns
    float x[8];
    for (int k = 0; k < 8; k++) {
      x[k] = (in[0] ? v[0][k] : 0.0f) + (in[1] ? v[1][k] : 0.0f);
      x[k] += __shfl_xor_sync(0xffffffffu, x[k], 8);
      x[k] += __shfl_xor_sync(0xffffffffu, x[k], 16);
    }
    if ((tid & 31) < 8)
      for (int k = 0; k < 8; k++) part[tid >> 5][(tid & 7) * 8 + k] = x[k];
  }
  float m = multiplier(t, partials, n_partials, headroom_max, scale);
  if (sum_partials && tid < 64 && c0 + tid < cols) {
    float s = part[0][tid];
    for (int w = 1; w < 8; w++) s += part[w][tid];
    sum_partials[row_tile * cols + c0 + tid] = s;
  }
  for (int i = 0; i < 2; i++) {
    int g = tid + 256 * i, tr = g >> 3, tc = (g & 7) * 8;
    unsigned int w[2] = {0u, 0u};
    if (in[i]) {
      for (int k = 0; k < 8; k += 2)
        w[k >> 2] |= (unsigned int)to_fp8x2<E5M2>(rounded(v[i][k] * m, t), rounded(v[i][k + 1] * m, t)) << (8 * (k & 3));
      if (q) *(uint2*)(q + (r0 + tr) * cols + c0 + tc) = make_uint2(w[0], w[1]);
    }
    *(unsigned int*)&tile[tr][tc] = w[0];
    *(unsigned int*)&tile[tr][tc + 4] = w[1];
  }
  if (!qt) return;  // the same for the whole block
  __syncthreads();
  const int tc = tid >> 2, tr = (tid & 3) * 16;  // the transpose's row c0 + tc, its columns r0 + tr ... + 15
  const long long c = c0 + tc, r = r0 + tr;
  if (c < cols && r < padded_rows) {
    unsigned int w[4];
    for (int k = 0; k < 4; k++)
      w[k] = (unsigned int)tile[tr + 4 * k][tc] | ((unsigned int)tile[tr + 4 * k + 1][tc] << 8) |
             ((unsigned int)tile[tr + 4 * k + 2][tc] << 16) | ((unsigned int)tile[tr + 4 * k + 3][tc] << 24);
    *(uint4*)(qt + c * padded_rows + r) = make_uint4(w[0], w[1], w[2], w[3]);
  }
}

#define QUANT(T) const T* t, const float* partials, long long n_partials, double headroom_max, unsigned char* q, unsigned char* qt, float* scale, float* sum_partials, long long rows, long long cols, long long padded_rows
#define QCALL(T, E) fp8_quantize<T, E>(t, partials, n_partials, (float)headroom_max, q, qt, scale, sum_partials, rows, cols, padded_rows)
extern "C" __global__ void fp8_quantize_f32_e4m3(QUANT(float)) { QCALL(float, false); }
extern "C" __global__ void fp8_quantize_f32_e5m2(QUANT(float)) { QCALL(float, true); }
extern "C" __global__ void fp8_quantize_bf16_e4m3(QUANT(unsigned short)) { QCALL(unsigned short, false); }
extern "C" __global__ void fp8_quantize_bf16_e5m2(QUANT(unsigned short)) { QCALL(unsigned short, true); }
#define QVEC(T, E) fp8_quantize_vec<T, E>(t, partials, n_partials, (float)headroom_max, q, qt, scale, sum_partials, rows, cols, padded_rows)
extern "C" __global__ void __launch_bounds__(256) fp8_quantize_vec_f32_e4m3(QUANT(float)) { QVEC(float, false); }
extern "C" __global__ void __launch_bounds__(256) fp8_quantize_vec_f32_e5m2(QUANT(float)) { QVEC(float, true); }
extern "C" __global__ void __launch_bounds__(256) fp8_quantize_vec_bf16_e4m3(QUANT(unsigned short)) { QVEC(unsigned short, false); }
extern "C" __global__ void __launch_bounds__(256) fp8_quantize_vec_bf16_e5m2(QUANT(unsigned short)) { QVEC(unsigned short, true); }
extern "C" __global__ void __launch_bounds__(1024) fp8_amax_f32(const float* t, long long n, float* partials, long long vec) { fp8_amax(t, n, partials, vec != 0); }
extern "C" __global__ void __launch_bounds__(1024) fp8_amax_bf16(const unsigned short* t, long long n, float* partials, long long vec) { fp8_amax(t, n, partials, vec != 0); }

// sums[c] = the sum over the `tiles` rows of sum_partials [tiles, cols] (column c), in a fixed
// order, in fp32, written as f32 or (bf16 set) rounded to bf16: a block of 32 x 8 threads per 32
// columns, each thread every eighth row from its own.
extern "C" __global__ void __launch_bounds__(256) column_sums(const float* __restrict__ sum_partials, long long tiles, long long cols, void* __restrict__ sums, long long bf16) {
  __shared__ float part[8][32];
  const long long c = (long long)blockIdx.x * 32 + threadIdx.x;
  float s = 0.0f;
  if (c < cols) {
#pragma unroll 4
    for (long long i = threadIdx.y; i < tiles; i += 8) s += sum_partials[i * cols + c];
  }
  part[threadIdx.y][threadIdx.x] = s;
  __syncthreads();
  if (threadIdx.y == 0 && c < cols) {
    for (int w = 1; w < 8; w++) s += part[w][threadIdx.x];
    if (bf16) ((unsigned short*)sums)[c] = to_bf16(s);
    else ((float*)sums)[c] = s;
  }
}
"#;

/// The virtual architecture NVRTC compiles for on a device of compute capability `major.minor`
/// (so that `__CUDA_ARCH__` lets the kernels use its instructions): the newest one NVRTC 13 knows
/// at or under the device's (PTX runs on later devices); None (NVRTC's default) under the oldest.
fn virtual_architecture(major: i32, minor: i32) -> Option<&'static str> {
    const KNOWN: [(i32, &str); 11] = [
        (75, "compute_75"),
        (80, "compute_80"),
        (86, "compute_86"),
        (87, "compute_87"),
        (89, "compute_89"),
        (90, "compute_90"),
        (100, "compute_100"),
        (103, "compute_103"),
        (110, "compute_110"),
        (120, "compute_120"),
        (121, "compute_121"),
    ];
    KNOWN.iter().rev().find(|(v, _)| *v <= major * 10 + minor).map(|(_, a)| *a)
}

/// `source` compiled with NVRTC without multiply-add contraction (each operation rounds on its
/// own, as CPU arithmetic and libtorch's tensor operations do) and loaded on CUDA device `index`;
/// `what` names it in errors.
pub fn load_module(index: usize, source: &str, what: &str) -> Result<(Arc<CudaContext>, Arc<CudaModule>)> {
    // SAFETY: probing a shared library by name.
    ensure!(unsafe { cudarc::nvrtc::sys::is_culib_present() }, "NVRTC (libnvrtc.so) is not on the library path");
    let ctx = CudaContext::new(index).context("binding the CUDA context")?;
    let (major, minor) = ctx.compute_capability().context("reading the device's compute capability")?;
    let options = cudarc::nvrtc::CompileOptions { fmad: Some(false), arch: virtual_architecture(major, minor), ..Default::default() };
    let ptx = cudarc::nvrtc::compile_ptx_with_opts(source, options).with_context(|| format!("compiling {what} with NVRTC"))?;
    let module = ctx.load_module(ptx).with_context(|| format!("loading {what}"))?;
    Ok((ctx, module))
}

pub(crate) struct Kernels {
    ctx: Arc<CudaContext>,
    // Holds the functions' module loaded.
    _module: Arc<CudaModule>,
    /// [f32, bf16] x [one pair, four pairs] per thread.
    rope: [[CudaFunction; 2]; 2],
    /// [f32, bf16].
    frame_forward: [CudaFunction; 2],
    frame_backward: [CudaFunction; 2],
    /// [f32, bf16] x [e4m3, e5m2]: any shape, and whole groups of values (`Fp8Shape::vectorizes`).
    fp8_quantize: [[CudaFunction; 2]; 2],
    fp8_quantize_vec: [[CudaFunction; 2]; 2],
    /// [f32, bf16].
    fp8_amax: [CudaFunction; 2],
    column_sums: CudaFunction,
}

impl Kernels {
    /// The kernels of CUDA device `index`, compiled at first use; the error (NVRTC missing, ...)
    /// is kept and repeated.
    pub(crate) fn for_device(index: usize) -> Result<Arc<Kernels>> {
        type Cache = Mutex<Vec<(usize, Result<Arc<Kernels>, String>)>>;
        static CACHE: OnceLock<Cache> = OnceLock::new();
        let mut cache = CACHE.get_or_init(Default::default).lock().map_err(|_| anyhow!("the fused kernels' cache is poisoned"))?;
        if let Some((_, k)) = cache.iter().find(|(i, _)| *i == index) {
            return k.clone().map_err(|e| anyhow!(e));
        }
        let made = Self::compile(index).map(Arc::new).map_err(|e| format!("{e:#}"));
        cache.push((index, made.clone()));
        made.map_err(|e| anyhow!(e))
    }

    fn compile(index: usize) -> Result<Kernels> {
        // Without contraction each product rounds as the CPU arithmetic's does.
        let (ctx, module) = load_module(index, SOURCE, "the fused kernels")?;
        let function = |name: &str| module.load_function(name).with_context(|| format!("the fused kernel {name}"));
        Ok(Kernels {
            rope: [[function("rope_f32_1")?, function("rope_f32_4")?], [function("rope_bf16_1")?, function("rope_bf16_4")?]],
            frame_forward: [function("frame_forward_f32")?, function("frame_forward_bf16")?],
            frame_backward: [function("frame_backward_f32")?, function("frame_backward_bf16")?],
            fp8_quantize: [
                [function("fp8_quantize_f32_e4m3")?, function("fp8_quantize_f32_e5m2")?],
                [function("fp8_quantize_bf16_e4m3")?, function("fp8_quantize_bf16_e5m2")?],
            ],
            fp8_quantize_vec: [
                [function("fp8_quantize_vec_f32_e4m3")?, function("fp8_quantize_vec_f32_e5m2")?],
                [function("fp8_quantize_vec_bf16_e4m3")?, function("fp8_quantize_vec_bf16_e5m2")?],
            ],
            fp8_amax: [function("fp8_amax_f32")?, function("fp8_amax_bf16")?],
            column_sums: function("column_sums")?,
            ctx,
            _module: module,
        })
    }

    /// Launches `f` on `stream` (a CUstream) with `args`, each 64 bits wide as the kernels declare
    /// them.
    fn launch(&self, f: &CudaFunction, stream: *mut c_void, grid: (u32, u32), threads: u32, args: Vec<u64>) -> Result<()> {
        self.launch_blocks(f, stream, grid, (threads, 1), args)
    }

    /// [`Kernels::launch`] with blocks of `threads.0` x `threads.1` threads.
    fn launch_blocks(&self, f: &CudaFunction, stream: *mut c_void, grid: (u32, u32), threads: (u32, u32), mut args: Vec<u64>) -> Result<()> {
        self.ctx.bind_to_thread().context("binding the CUDA context")?;
        let mut params: Vec<*mut c_void> = args.iter_mut().map(|a| a as *mut u64 as *mut c_void).collect();
        // SAFETY: the callers pass live contiguous device buffers of the sizes their kernels read and
        // write (checked by the C++ side), used in order on libtorch's current stream, and one
        // 64-bit value per kernel parameter.
        unsafe { cudarc::driver::result::launch_kernel(f.cu_function(), (grid.0, grid.1, 1), (threads.0, threads.1, 1), 0, stream as cudarc::driver::sys::CUstream, &mut params) }
            .context("launching a fused kernel")
    }

    /// Rotates x into out (device addresses of contiguous buffers of `s`'s pairs, bf16 or f32)
    /// by the complex64 table at `rotations`: one block per token.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn rotate(&self, stream: *mut c_void, bf16: bool, x: u64, rotations: u64, out: u64, s: Shape, inverse: bool) -> Result<()> {
        let n = if s.pairs % 4 == 0 { 4 } else { 1 };
        let (groups, per_head) = (s.heads * s.pairs / n, s.pairs / n);
        ensure!(groups <= i32::MAX as i64 && s.len <= i32::MAX as i64, "rotary kernel: too many pairs per token or tokens");
        let blocks = u32::try_from(s.tokens).ok().filter(|&b| b < 1 << 31).context("rotary kernel: too many tokens for one launch")?;
        let threads = (groups as u32).div_ceil(32).clamp(1, 4) * 32;
        let f = &self.rope[bf16 as usize][(n == 4) as usize];
        self.launch(f, stream, (blocks, 1), threads, vec![x, rotations, out, s.len as u64, groups as u64, per_head as u64, inverse as u64])
    }

    /// out = a + b * c; `buffers` = [a, b, c, out].
    pub(crate) fn frame_forward(&self, stream: *mut c_void, bf16: bool, buffers: [u64; 4], a_per_frame: bool, s: FrameShape) -> Result<()> {
        let groups = (s.frames * s.rows * s.dim / 8) as u64;
        let blocks = groups.div_ceil(256).clamp(1, 132 * 16) as u32;
        let [a, b, c, out] = buffers;
        self.launch(&self.frame_forward[bf16 as usize], stream, (blocks, 1), 256, vec![a, a_per_frame as u64, b, c, out, s.frames as u64, s.rows as u64, s.dim as u64 / 8])
    }

    /// db = g * c and the runs' partial sums of g * b (and of g unless that address is 0);
    /// `buffers` = [g, b, c, db, partial sums of g * b, partial sums of g].
    pub(crate) fn frame_backward(&self, stream: *mut c_void, bf16: bool, buffers: [u64; 6], s: FrameShape) -> Result<()> {
        let runs = (s.rows + s.rows_per_sum - 1) / s.rows_per_sum;
        let frames = u32::try_from(s.frames).ok().filter(|&f| f < 1 << 31).context("frame kernel: too many frames for one launch")?;
        let runs = u32::try_from(runs).ok().filter(|&r| r < 65_536).context("frame kernel: too many rows per frame for one launch")?;
        let threads = ((s.dim / 8) as u32).div_ceil(32).clamp(1, 16) * 32;
        let [g, b, c, db, pc, pa] = buffers;
        self.launch(&self.frame_backward[bf16 as usize], stream, (frames, runs), threads, vec![g, b, c, db, pc, pa, s.rows as u64, s.dim as u64 / 8, s.rows_per_sum as u64])
    }

    /// float8 values of t [rows, cols] (bf16 or f32) scaled by `headroom_max` over its largest
    /// magnitude: row-major into `q` and transposed, zero-padded to `padded_rows` columns, into
    /// `qt` (either address 0: not written), 1 / the multiplier into the f32 at `scale`; `buffers`
    /// = [t, partials, q, qt, scale], `partials` room for `n_partials` f32 (the largest magnitude's
    /// partial maxima, one per block of the first kernel, which the second reduces). `sums`, where
    /// given, = (scratch of `Fp8Shape::sum_partials` f32, the [cols] of t's dtype that receive t's
    /// column sums): the second kernel sums each tile's columns as it reads them, a third adds the
    /// tiles.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn fp8_quantize(
        &self,
        stream: *mut c_void,
        bf16: bool,
        e5m2: bool,
        buffers: [u64; 5],
        sums: Option<(u64, u64)>,
        n_partials: i64,
        headroom_max: f64,
        s: Fp8Shape,
    ) -> Result<()> {
        ensure!(s.padded_rows >= s.rows, "FP8 quantization: {} padded rows for {} rows", s.padded_rows, s.rows);
        let blocks = u32::try_from(n_partials).ok().filter(|b| (1..=65_535).contains(b)).context("FP8 quantization: 1 to 65535 partial maxima")?;
        let [t, partials, q, qt, scale] = buffers;
        let n = s.rows * s.cols;
        let whole_groups = n % 8 == 0 && t % 16 == 0;
        self.launch(&self.fp8_amax[bf16 as usize], stream, (blocks, 1), 1024, vec![t, n as u64, partials, whole_groups as u64])?;
        let vec = s.vectorizes(buffers);
        let (f, tile, threads) = if vec {
            (&self.fp8_quantize_vec[bf16 as usize][e5m2 as usize], 64, (256, 1))
        } else {
            (&self.fp8_quantize[bf16 as usize][e5m2 as usize], 32, (32, 8))
        };
        // At least one block, also for an empty t: it writes the scale (as the CPU loop does).
        let row_tiles = u32::try_from((s.padded_rows + tile - 1) / tile).ok().filter(|&b| b < 1 << 31).context("FP8 quantization: too many rows for one launch")?.max(1);
        let col_tiles = u32::try_from((s.cols + tile - 1) / tile).ok().filter(|&b| b < 65_536).context("FP8 quantization: too many columns for one launch")?.max(1);
        let (sum_partials, column_sums) = sums.unwrap_or((0, 0));
        let args = vec![t, partials, n_partials as u64, headroom_max.to_bits(), q, qt, scale, sum_partials, s.rows as u64, s.cols as u64, s.padded_rows as u64];
        self.launch_blocks(f, stream, (row_tiles, col_tiles), threads, args)?;
        if sums.is_some() {
            let blocks = u32::try_from((s.cols + 31) / 32).ok().filter(|&b| b < 1 << 31).context("FP8 quantization: too many columns to sum")?;
            self.launch_blocks(&self.column_sums, stream, (blocks.max(1), 1), (32, 8), vec![sum_partials, row_tiles as u64, s.cols as u64, column_sums, bf16 as u64])?;
        }
        Ok(())
    }
}
