// y = x W^T + b with the three matmuls of a linear layer's step in float8, as torchao's float8
// "tensorwise" training recipe does: x and W cast to e4m3 and the incoming gradient to e5m2, each
// with one scale from its own absolute maximum on every call (dynamic scaling); products by
// _scaled_mm, accumulated in fp32 and returned in the inputs' dtype. The bias and its gradient
// stay in that dtype.
#include <torch/torch.h>

#include <cfloat>
#include <limits>
#include <string>

namespace {

constexpr double E4M3_MAX = 448.0;
constexpr double E5M2_MAX = 57344.0;

struct Quantized {
  at::Tensor q;      // float8
  at::Tensor scale;  // f32 scalar: t ~= q * scale
};

// Two passes over t: its largest magnitude (the infinity norm, one reduction without a temporary),
// then the product with the multiplier written straight into float8. The casts do not saturate,
// so the multiplier aims a little under the format's largest value: rounded to t's dtype (2^-8
// relative for bf16) and the product rounded again, |t| * multiplier stays under fmax. The scale is
// the multiplier's exact inverse.
Quantized quantize(const at::Tensor& t, at::ScalarType fp8, double fmax) {
  constexpr double HEADROOM = 1.0 - 1.0 / 64;
  auto amax = at::linalg_vector_norm(t, std::numeric_limits<double>::infinity()).to(at::kFloat);
  auto multiplier = (fmax * HEADROOM / amax.clamp_min(1e-12)).clamp_max(FLT_MAX).to(t.scalar_type());
  auto q = at::empty(t.sizes(), t.options().dtype(fp8));
  at::mul_out(q, t, multiplier);
  return {q, multiplier.to(at::kFloat).reciprocal()};
}

// [rows, cols] -> its transpose [cols, padded(rows)] row-major, the padding columns zero: the
// operands of the weight's gradient, whose inner dimension (x's rows) CUDA's FP8 matmuls need a
// multiple of 16 (zero rows of x and of the gradient add nothing to g^T x).
int64_t padded(int64_t m) { return (m + 15) / 16 * 16; }
at::Tensor transposed_padded(const at::Tensor& q) {
  const int64_t m = q.size(0), mp = padded(m);
  if (mp == m) return q.t().contiguous();
  auto t = at::empty({q.size(1), mp}, q.options());
  t.narrow(1, 0, m).copy_(q.t());
  t.narrow(1, m, mp - m).zero_();
  return t;
}

// _scaled_mm adds a bias of the output's dtype in its epilogue for bf16 and fp16 outputs only.
bool bias_in_product(const at::Tensor& x) { return x.scalar_type() == at::kBFloat16 || x.scalar_type() == at::kHalf; }

struct Fp8Linear : public torch::autograd::Function<Fp8Linear> {
  static at::Tensor forward(torch::autograd::AutogradContext* ctx, const at::Tensor& x, const at::Tensor& w, const at::Tensor& b) {
    auto xq = quantize(x.contiguous(), at::kFloat8_e4m3fn, E4M3_MAX);
    auto wq = quantize(w, at::kFloat8_e4m3fn, E4M3_MAX);
    ctx->save_for_backward({xq.q, xq.scale, wq.q, wq.scale});
    ctx->saved_data["w_dtype"] = static_cast<int64_t>(w.scalar_type());
    // y [m, out] = x [m, in] W^T; the second operand column-major, as _scaled_mm needs it.
    if (bias_in_product(x)) {
      return at::_scaled_mm(xq.q, wq.q.t(), xq.scale, wq.scale, b.to(x.scalar_type()), std::nullopt, x.scalar_type(), true);
    }
    return at::_scaled_mm(xq.q, wq.q.t(), xq.scale, wq.scale, std::nullopt, std::nullopt, x.scalar_type(), true) + b.to(x.scalar_type());
  }

  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx, torch::autograd::variable_list grads) {
    auto saved = ctx->get_saved_variables();
    const auto &xq = saved[0], &x_scale = saved[1], &wq = saved[2], &w_scale = saved[3];
    const auto w_dtype = static_cast<at::ScalarType>(ctx->saved_data["w_dtype"].toInt());
    auto g = grads[0].contiguous();
    auto gb = g.sum(0).to(w_dtype);
    auto gq = quantize(g, at::kFloat8_e5m2, E5M2_MAX);
    // dL/dx [m, in] = g [m, out] W [out, in] (W column-major: its transpose row-major);
    // dL/dW [out, in] = g^T [out, m] x [m, in] (x column-major).
    auto gx = at::_scaled_mm(gq.q, wq.t().contiguous().t(), gq.scale, w_scale, std::nullopt, std::nullopt, g.scalar_type(), false);
    auto gw = at::_scaled_mm(transposed_padded(gq.q), transposed_padded(xq).t(), gq.scale, x_scale, std::nullopt, std::nullopt, w_dtype, false);
    return {gx, gw, gb};
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
