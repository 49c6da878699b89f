// The fused operations as autograd functions. Each pass is the Rust side's, handed in once as a
// function pointer (`bwm_fused_ops_set_passes`): on CUDA a kernel, on the CPU a loop or, for the
// frame operation, the same arithmetic in libtorch's tensors. This file holds no kernel.
#include <torch/torch.h>
#ifdef BWM_CUDA
#include <c10/cuda/CUDAStream.h>
#endif
#include <cstdint>
#include <string>

#include "bwm_guarded.h"

namespace {
// stream (CUDA; null on the CPU), device index (-1: CPU), dtype (0: f32, 1: bf16), x, rotations,
// out, tokens (B * L), L, heads, pairs per head, inverse, error buffer, its size -> 0 or an error.
using RopePass = int (*)(void*, int, int, const void*, const void*, void*, int64_t, int64_t, int64_t, int64_t, int, char*, size_t);
// stream, device index, dtype, then the forward (backward null) a, a per frame?, b, c, out, or the
// backward (forward null) g, b, c, db, partial sums of g * b and of g (null: a is whole), then
// frames (B * F), rows per frame (P), width (D), rows per partial sum, error buffer, its size.
using FramePass = int (*)(void*, int, int, const void*, int, const void*, const void*, void*, const void*, const void*, const void*, void*, float*, float*, int64_t, int64_t, int64_t, int64_t, char*, size_t);
RopePass rope_pass = nullptr;
FramePass frame_pass = nullptr;
// The frame operation's backward sums the rows of each frame in runs of this many.
constexpr int64_t kRowsPerSum = 16;

// The kernels read 16 bytes at a time from a tensor's start.
at::Tensor aligned(const at::Tensor& t) {
  return t.is_contiguous() && reinterpret_cast<std::uintptr_t>(t.const_data_ptr()) % 16 == 0 ? t : t.clone(at::MemoryFormat::Contiguous);
}

int dtype_code(const at::Tensor& t) {
  TORCH_CHECK(t.scalar_type() == at::kFloat || t.scalar_type() == at::kBFloat16, "the fused operations take f32 or bf16, got ", t.scalar_type());
  return t.scalar_type() == at::kBFloat16 ? 1 : 0;
}

// The stream and device index of x's device (null and -1 on the CPU).
std::pair<void*, int> stream_of(const at::Tensor& x) {
  if (x.is_cuda()) {
#ifdef BWM_CUDA
    const int device = x.device().index();
    return {c10::cuda::getCurrentCUDAStream(static_cast<c10::DeviceIndex>(device)).stream(), device};
#else
    TORCH_CHECK(false, "this build's libtorch has no CUDA");
#endif
  }
  TORCH_CHECK(x.is_cpu(), "the fused operations run on the CPU or a CUDA device, got ", x.device());
  return {nullptr, -1};
}

// x [B, L, heads, 2 * pairs]; rotations complex64 of L * pairs elements ([L, 1, pairs]).
at::Tensor rotate(const at::Tensor& input, const at::Tensor& rotations, bool inverse) {
  TORCH_CHECK(rope_pass != nullptr, "the passes were not set");
  TORCH_CHECK(input.dim() == 4, "x must be [B, L, heads, head_dim], got ", input.sizes());
  const auto x = aligned(input);
  const int64_t b = x.size(0), l = x.size(1), heads = x.size(2), d = x.size(3);
  TORCH_CHECK(d % 2 == 0, "the head dimension must be even, got ", d);
  const int dtype = dtype_code(x);
  TORCH_CHECK(rotations.scalar_type() == at::kComplexFloat, "the rotations must be complex64, got ", rotations.scalar_type());
  TORCH_CHECK(rotations.numel() == l * (d / 2), "the rotations hold ", rotations.numel(), " values for ", l, " tokens of ", d / 2, " pairs");
  TORCH_CHECK(rotations.device() == x.device(), "the rotations are on ", rotations.device(), ", x on ", x.device());
  const auto r = aligned(rotations);
  auto out = at::empty_like(x);
  if (x.numel() == 0) return out;
  const auto [stream, device] = stream_of(x);
  char err[512] = {0};
  const int rc = rope_pass(stream, device, dtype, x.const_data_ptr(), r.const_data_ptr(), out.mutable_data_ptr(), b * l, l, heads, d / 2, inverse ? 1 : 0, err, sizeof(err) - 1);
  TORCH_CHECK(rc == 0, err);
  return out;
}

struct Rope : public torch::autograd::Function<Rope> {
  static at::Tensor forward(torch::autograd::AutogradContext* ctx, const at::Tensor& x, const at::Tensor& rotations) {
    ctx->saved_data["rotations"] = rotations;
    return rotate(x, rotations, false);
  }
  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx, torch::autograd::variable_list grads) {
    return {rotate(grads[0], ctx->saved_data["rotations"].toTensor(), true), at::Tensor()};
  }
};

// Checks a + b * c: b [B, F, P, D]; c [B, F, 1, D]; a as b or as c; one dtype, one device, D a
// multiple of 8. Returns (B * F, P, D).
std::tuple<int64_t, int64_t, int64_t> frame_shape(const at::Tensor& a, const at::Tensor& b, const at::Tensor& c) {
  TORCH_CHECK(b.dim() == 4, "b must be [B, F, P, D], got ", b.sizes());
  const int64_t bs = b.size(0), f = b.size(1), p = b.size(2), d = b.size(3);
  TORCH_CHECK(d % 8 == 0, "the width must be a multiple of 8, got ", d);
  const std::vector<int64_t> per_frame = {bs, f, 1, d};
  TORCH_CHECK(c.sizes() == at::IntArrayRef(per_frame), "c must be ", at::IntArrayRef(per_frame), ", got ", c.sizes());
  TORCH_CHECK(a.sizes() == b.sizes() || a.sizes() == at::IntArrayRef(per_frame), "a must be ", b.sizes(), " or ", at::IntArrayRef(per_frame), ", got ", a.sizes());
  TORCH_CHECK(a.scalar_type() == b.scalar_type() && c.scalar_type() == b.scalar_type(), "a, b and c must share a dtype, got ", a.scalar_type(), ", ", b.scalar_type(), ", ", c.scalar_type());
  TORCH_CHECK(a.device() == b.device() && c.device() == b.device(), "a, b and c must share a device");
  dtype_code(b);
  return {bs * f, p, d};
}

struct FrameAddcmul : public torch::autograd::Function<FrameAddcmul> {
  static at::Tensor forward(torch::autograd::AutogradContext* ctx, const at::Tensor& a_in, const at::Tensor& b_in, const at::Tensor& c_in) {
    TORCH_CHECK(frame_pass != nullptr, "the passes were not set");
    const auto [frames, rows, d] = frame_shape(a_in, b_in, c_in);
    const auto a = aligned(a_in), b = aligned(b_in), c = aligned(c_in);
    const bool a_whole = a.sizes() == b.sizes();
    ctx->save_for_backward({b, c});
    ctx->saved_data["a_whole"] = a_whole;
    if (b.is_cpu() || b.numel() == 0) {
      const auto f = [](const at::Tensor& t) { return t.to(at::kFloat); };
      return (f(a) + f(b) * f(c)).to(b.scalar_type());
    }
    auto out = at::empty_like(b);
    const auto [stream, device] = stream_of(b);
    char err[512] = {0};
    const int rc = frame_pass(stream, device, dtype_code(b), a.const_data_ptr(), a_whole ? 0 : 1, b.const_data_ptr(), c.const_data_ptr(), out.mutable_data_ptr(),
                              nullptr, nullptr, nullptr, nullptr, nullptr, nullptr, frames, rows, d, kRowsPerSum, err, sizeof(err) - 1);
    TORCH_CHECK(rc == 0, err);
    return out;
  }

  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx, torch::autograd::variable_list grads) {
    const auto saved = ctx->get_saved_variables();
    const auto &b = saved[0], &c = saved[1];
    const bool a_whole = ctx->saved_data["a_whole"].toBool();
    const auto g = aligned(grads[0]);
    const int64_t frames = b.size(0) * b.size(1), rows = b.size(2), d = b.size(3);
    const auto per_frame = c.sizes();
    if (b.is_cpu() || b.numel() == 0) {
      const auto f = [](const at::Tensor& t) { return t.to(at::kFloat); };
      const auto gf = f(g);
      auto db = (gf * f(c)).to(b.scalar_type());
      auto dc = (gf * f(b)).sum(2, true).to(b.scalar_type());
      auto da = a_whole ? g : gf.sum(2, true).to(b.scalar_type());
      return {da, db, dc};
    }
    const int64_t runs = (rows + kRowsPerSum - 1) / kRowsPerSum;
    auto db = at::empty_like(b);
    const auto sums = b.options().dtype(at::kFloat);
    auto partial_c = at::empty({frames, runs, d}, sums);
    auto partial_a = a_whole ? at::Tensor() : at::empty({frames, runs, d}, sums);
    const auto [stream, device] = stream_of(b);
    char err[512] = {0};
    const int rc = frame_pass(stream, device, dtype_code(b), nullptr, 0, nullptr, nullptr, nullptr, g.const_data_ptr(), b.const_data_ptr(), c.const_data_ptr(), db.mutable_data_ptr(),
                              partial_c.mutable_data_ptr<float>(), a_whole ? nullptr : partial_a.mutable_data_ptr<float>(), frames, rows, d, kRowsPerSum, err, sizeof(err) - 1);
    TORCH_CHECK(rc == 0, err);
    auto dc = partial_c.sum(1).to(b.scalar_type()).view(per_frame);
    auto da = a_whole ? grads[0] : partial_a.sum(1).to(b.scalar_type()).view(per_frame);
    return {da, db, dc};
  }
};
}  // namespace

extern "C" {

void bwm_fused_ops_set_passes(RopePass rope, FramePass frame) {
  rope_pass = rope;
  frame_pass = frame;
}

// Each writes a new tensor to *out and returns null, or returns the error's message (valid until
// the thread's next call).
const char* bwm_fused_rope(const at::Tensor* x, const at::Tensor* rotations, at::Tensor** out) {
  if (guarded([&] { *out = new at::Tensor(Rope::apply(*x, *rotations)); })) return nullptr;
  return last_error.c_str();
}

const char* bwm_fused_frame_addcmul(const at::Tensor* a, const at::Tensor* b, const at::Tensor* c, at::Tensor** out) {
  if (guarded([&] { *out = new at::Tensor(FrameAddcmul::apply(*a, *b, *c)); })) return nullptr;
  return last_error.c_str();
}

}
