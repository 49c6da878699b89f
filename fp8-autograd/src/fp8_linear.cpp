// y = x W^T + b with the three matmuls of a linear layer's step in float8, as torchao's float8
// "tensorwise" training recipe does: x and W cast to e4m3 and the incoming gradient to e5m2, each
// with one scale from its own absolute maximum on every call (dynamic scaling); products by
// _scaled_mm, accumulated in fp32 and returned in the inputs' dtype. The bias and its gradient
// stay in that dtype.
#include <torch/torch.h>

#include <cfloat>
#include <string>

namespace {

constexpr double E4M3_MAX = 448.0;
constexpr double E5M2_MAX = 57344.0;

struct Quantized {
  at::Tensor q;      // float8
  at::Tensor scale;  // f32 scalar: t ~= q * scale
};

// The multiplier is rounded to t's dtype first and the scale is its exact inverse; the clamp keeps
// a product rounded past the format's largest value from becoming NaN (the casts do not saturate).
Quantized quantize(const at::Tensor& t, at::ScalarType fp8, double fmax) {
  auto amax = t.abs().max().to(at::kFloat);
  auto multiplier = (fmax / amax.clamp_min(1e-12)).clamp_max(FLT_MAX).to(t.scalar_type());
  auto scale = multiplier.to(at::kFloat).reciprocal();
  return {(t * multiplier).clamp(-fmax, fmax).to(fp8), scale};
}

// _scaled_mm's second operand must be column-major.
at::Tensor column_major(const at::Tensor& t) { return t.t().contiguous().t(); }

// CUDA's FP8 matmuls need every dimension a multiple of 16: rows of zeros added to x (and so to the
// gradient) change neither amax nor the other rows' products.
int64_t padded(int64_t m) { return (m + 15) / 16 * 16; }

struct Fp8Linear : public torch::autograd::Function<Fp8Linear> {
  static at::Tensor forward(torch::autograd::AutogradContext* ctx, const at::Tensor& x, const at::Tensor& w, const at::Tensor& b) {
    const int64_t m = x.size(0);
    auto xp = x.contiguous();
    if (padded(m) != m) xp = at::constant_pad_nd(xp, {0, 0, 0, padded(m) - m});
    auto xq = quantize(xp, at::kFloat8_e4m3fn, E4M3_MAX);
    auto wq = quantize(w, at::kFloat8_e4m3fn, E4M3_MAX);
    auto y = at::_scaled_mm(xq.q, wq.q.t(), xq.scale, wq.scale, std::nullopt, std::nullopt, x.scalar_type(), true);
    ctx->save_for_backward({xq.q, xq.scale, wq.q, wq.scale});
    ctx->saved_data["w_dtype"] = static_cast<int64_t>(w.scalar_type());
    return y.narrow(0, 0, m) + b.to(x.scalar_type());
  }

  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx, torch::autograd::variable_list grads) {
    auto saved = ctx->get_saved_variables();
    const auto &xq = saved[0], &x_scale = saved[1], &wq = saved[2], &w_scale = saved[3];
    const auto w_dtype = static_cast<at::ScalarType>(ctx->saved_data["w_dtype"].toInt());
    auto g = grads[0].contiguous();
    const int64_t m = g.size(0);  // x's rows before padding
    auto gb = g.sum(0).to(w_dtype);
    if (padded(m) != m) g = at::constant_pad_nd(g, {0, 0, 0, padded(m) - m});
    auto gq = quantize(g, at::kFloat8_e5m2, E5M2_MAX);
    // dL/dx [m, in] = g [m, out] W [out, in]; dL/dW [out, in] = g^T [out, m] x [m, in].
    auto gx = at::_scaled_mm(gq.q, column_major(wq), gq.scale, w_scale, std::nullopt, std::nullopt, g.scalar_type(), false);
    auto gw = at::_scaled_mm(gq.q.t().contiguous(), column_major(xq), gq.scale, x_scale, std::nullopt, std::nullopt, w_dtype, false);
    return {gx.narrow(0, 0, m), gw, gb};
  }
};

thread_local std::string last_error;

}  // namespace

extern "C" {

// x [m, in], w [out, in], b [out]; writes a new tensor [m, out] to *out and returns null, or
// returns the error's message (valid until the thread's next call).
const char* bwm_fp8_linear(const at::Tensor* x, const at::Tensor* w, const at::Tensor* b, at::Tensor** out) {
  try {
    *out = new at::Tensor(Fp8Linear::apply(*x, *w, *b));
    return nullptr;
  } catch (const std::exception& e) {
    last_error = e.what();
    return last_error.c_str();
  }
}

}
