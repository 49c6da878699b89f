// The rotation as an autograd function: forward rotates by the rotations, backward by their
// conjugates (a rotation's transpose is its inverse). The pass itself is the Rust side's, handed
// in once as a function pointer (`bwm_fused_rope_set_pass`), so that this file holds no kernel.
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
using Pass = int (*)(void*, int, int, const void*, const void*, void*, int64_t, int64_t, int64_t, int64_t, int, char*, size_t);
Pass pass = nullptr;

// x [B, L, heads, 2 * pairs]; rotations complex64 of L * pairs elements ([L, 1, pairs]).
at::Tensor rotate(const at::Tensor& input, const at::Tensor& rotations, bool inverse) {
  TORCH_CHECK(pass != nullptr, "the rotation pass was not set");
  TORCH_CHECK(input.dim() == 4, "x must be [B, L, heads, head_dim], got ", input.sizes());
  // The kernel reads 16 bytes at a time from a tensor's start.
  const auto aligned = [](const at::Tensor& t) {
    return t.is_contiguous() && reinterpret_cast<std::uintptr_t>(t.const_data_ptr()) % 16 == 0 ? t : t.clone(at::MemoryFormat::Contiguous);
  };
  const auto x = aligned(input);
  const int64_t b = x.size(0), l = x.size(1), heads = x.size(2), d = x.size(3);
  TORCH_CHECK(d % 2 == 0, "the head dimension must be even, got ", d);
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kBFloat16, "x must be f32 or bf16, got ", x.scalar_type());
  TORCH_CHECK(rotations.scalar_type() == at::kComplexFloat, "the rotations must be complex64, got ", rotations.scalar_type());
  TORCH_CHECK(rotations.numel() == l * (d / 2), "the rotations hold ", rotations.numel(), " values for ", l, " tokens of ", d / 2, " pairs");
  TORCH_CHECK(rotations.device() == x.device(), "the rotations are on ", rotations.device(), ", x on ", x.device());
  const auto r = aligned(rotations);
  auto out = at::empty_like(x);
  if (x.numel() == 0) return out;
  void* stream = nullptr;
  int device = -1;
  if (x.is_cuda()) {
#ifdef BWM_CUDA
    device = x.device().index();
    stream = c10::cuda::getCurrentCUDAStream(static_cast<c10::DeviceIndex>(device)).stream();
#else
    TORCH_CHECK(false, "this build's libtorch has no CUDA");
#endif
  } else {
    TORCH_CHECK(x.is_cpu(), "x must be on the CPU or a CUDA device, got ", x.device());
  }
  char err[512] = {0};
  const int dtype = x.scalar_type() == at::kBFloat16 ? 1 : 0;
  const int rc = pass(stream, device, dtype, x.const_data_ptr(), r.const_data_ptr(), out.mutable_data_ptr(), b * l, l, heads, d / 2, inverse ? 1 : 0, err, sizeof(err) - 1);
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
}  // namespace

extern "C" {

void bwm_fused_rope_set_pass(Pass p) { pass = p; }

// Writes a new tensor to *out and returns null, or returns the error's message (valid until the
// thread's next call).
const char* bwm_fused_rope(const at::Tensor* x, const at::Tensor* rotations, at::Tensor** out) {
  if (guarded([&] { *out = new at::Tensor(Rope::apply(*x, *rotations)); })) return nullptr;
  return last_error.c_str();
}

}
