// y = x W^T + b with the three matmuls of a linear layer's step in float8, as torchao's float8
// "tensorwise" training recipe does: x and W cast to e4m3 and the incoming gradient to e5m2, each
// with one scale from its own absolute maximum on every call (dynamic scaling); products by
// _scaled_mm, accumulated in fp32 and returned in the inputs' dtype. The bias and its gradient
// stay in that dtype. The cast (with the scale's arithmetic and the transposed copy the products
// need) is the Rust side's pass, handed in once as a function pointer (`bwm_fp8_set_quantize_pass`):
// bwm-fused-ops' kernel on CUDA, its loop on the CPU.
#include <torch/torch.h>
#ifdef BWM_CUDA
#include <c10/cuda/CUDAStream.h>
#endif

#include <algorithm>
#include <cstdint>
#include <mutex>
#include <optional>
#include <string>

namespace {

constexpr double E4M3_MAX = 448.0;
constexpr double E5M2_MAX = 57344.0;

// stream (CUDA; null on the CPU), device index (-1: CPU), dtype (0: f32, 1: bf16), format (0:
// e4m3fn, 1: e5m2), the multiplier's target, t, scratch for the largest magnitude's partial maxima
// on t's device (f32) and their number, q, its transpose, the scale, scratch for the column sums
// (f32) and its size, the column sums ([cols] of t's dtype; null: none), rows, cols, the
// transpose's padded rows, error buffer, its size -> 0 or an error.
using QuantizePass = int (*)(void*, int, int, int, double, const void*, float*, int64_t, uint8_t*, uint8_t*, float*, float*, int64_t, void*, int64_t,
                             int64_t, int64_t, char*, size_t);
QuantizePass quantize_pass = nullptr;

struct Quantized {
  at::Tensor q;      // float8 [rows, cols], where asked for
  at::Tensor qt;     // its transpose [cols, padded rows], the padding zero, where asked for
  at::Tensor scale;  // f32 scalar: t ~= q * scale
  at::Tensor sums;   // [cols] of t's dtype: t's column sums (added in fp32), where asked for
};

// Rows of a transposed operand: the inner dimension of the weight's gradient (x's rows), which
// CUDA's FP8 matmuls need a multiple of 16 (zero rows of x and of the gradient add nothing to g^T x).
int64_t padded(int64_t m) { return (m + 15) / 16 * 16; }

// t [rows, cols] in float8 `fp8` with one scale from its largest magnitude, all in the pass: on
// CUDA a reduction into PARTIALS partial maxima, then one kernel that reduces them to the
// multiplier and writes each value's product, cast, and the transpose. The casts
// do not saturate, so the multiplier aims a little under the format's largest value: rounded to
// t's dtype (2^-8 relative for bf16) and the product rounded again, |t| * multiplier stays under
// fmax. The scale is the multiplier's exact inverse. want_sums: t's column sums too (a bias's
// gradient), read in the same pass instead of a reduction of its own.
Quantized quantize(const at::Tensor& input, at::ScalarType fp8, double fmax, bool want_q, bool want_qt, bool pad, bool want_sums = false) {
  constexpr double HEADROOM = 1.0 - 1.0 / 64;
  TORCH_CHECK(quantize_pass != nullptr, "the quantization pass was not set");
  TORCH_CHECK(input.dim() == 2, "FP8 quantization takes [rows, cols], got ", input.sizes());
  TORCH_CHECK(input.scalar_type() == at::kFloat || input.scalar_type() == at::kBFloat16, "FP8 quantization takes f32 or bf16, got ", input.scalar_type());
  const auto t = input.contiguous();
  const int64_t rows = t.size(0), cols = t.size(1), prows = pad ? padded(rows) : rows;
  const int64_t partials_n = t.is_cuda() ? 256 : 0;  // the CPU loop needs none
  const auto partials = at::empty({partials_n}, t.options().dtype(at::kFloat));
  Quantized out;
  const auto f8 = t.options().dtype(fp8);
  if (want_q) out.q = at::empty({rows, cols}, f8);
  if (want_qt) out.qt = at::empty({cols, prows}, f8);
  out.scale = at::empty({}, t.options().dtype(at::kFloat));
  // Scratch of the column sums on CUDA: a row of cols per tile of 32 (padded) rows, at least one.
  const int64_t sum_partials_n = want_sums && t.is_cuda() ? std::max<int64_t>(1, (prows + 31) / 32) * cols : 0;
  const auto sum_partials = at::empty({sum_partials_n}, t.options().dtype(at::kFloat));
  if (want_sums) out.sums = at::empty({cols}, t.options());
  void* stream = nullptr;
  int device = -1;
  if (t.is_cuda()) {
#ifdef BWM_CUDA
    device = t.device().index();
    stream = c10::cuda::getCurrentCUDAStream(static_cast<c10::DeviceIndex>(device)).stream();
#else
    TORCH_CHECK(false, "this build's libtorch has no CUDA");
#endif
  } else {
    TORCH_CHECK(t.is_cpu(), "FP8 quantization runs on the CPU or a CUDA device, got ", t.device());
  }
  std::string err(512, '\0');
  const int failed = quantize_pass(stream, device, t.scalar_type() == at::kBFloat16 ? 1 : 0, fp8 == at::kFloat8_e5m2 ? 1 : 0, fmax * HEADROOM,
                                   t.const_data_ptr(), partials.data_ptr<float>(), partials_n, want_q ? static_cast<uint8_t*>(out.q.data_ptr()) : nullptr,
                                   want_qt ? static_cast<uint8_t*>(out.qt.data_ptr()) : nullptr, out.scale.data_ptr<float>(),
                                   sum_partials.data_ptr<float>(), sum_partials_n, want_sums ? out.sums.data_ptr() : nullptr, rows, cols,
                                   prows, err.data(), err.size() - 1);
  TORCH_CHECK(!failed, "FP8 quantization: ", err.c_str());
  return out;
}

// The last input quantized for a forward product and its quantization, reused while the same
// values come again: a block's q, k and v projections read one tensor, as do the cross-
// attention's k and v. The same values: the same storage, place, shape, strides and dtype, and no
// write since (the version counter, which views share). Holding the input keeps its storage from
// being reused; the first backward drops it.
struct LastInput {
  at::Tensor x;
  int64_t version = 0;
  Quantized xq;
};
std::mutex last_input_lock;
std::optional<LastInput> last_input;

bool same_values(const at::Tensor& a, const at::Tensor& b) {
  return a.is_alias_of(b) && a.data_ptr() == b.data_ptr() && a.sizes() == b.sizes() && a.strides() == b.strides() &&
         a.scalar_type() == b.scalar_type() && a.device() == b.device();
}

Quantized quantize_input(const at::Tensor& x) {
  std::lock_guard<std::mutex> guard(last_input_lock);
  if (last_input && same_values(last_input->x, x) && last_input->version == x._version()) return last_input->xq;
  auto xq = quantize(x, at::kFloat8_e4m3fn, E4M3_MAX, true, true, true);
  last_input = LastInput{x, x._version(), xq};
  return xq;
}

void forget_last_input() {
  std::lock_guard<std::mutex> guard(last_input_lock);
  last_input.reset();
}

// _scaled_mm adds a bias of the output's dtype in its epilogue for bf16 and fp16 outputs only.
bool bias_in_product(const at::Tensor& x) { return x.scalar_type() == at::kBFloat16 || x.scalar_type() == at::kHalf; }

struct Fp8Linear : public torch::autograd::Function<Fp8Linear> {
  static at::Tensor forward(torch::autograd::AutogradContext* ctx, const at::Tensor& x, const at::Tensor& w, const at::Tensor& b) {
    // The backward needs x^T (padded) for W's gradient and W^T for x's: made in the same passes,
    // and kept instead of x and W in float8.
    auto xq = quantize_input(x);
    auto wq = quantize(w, at::kFloat8_e4m3fn, E4M3_MAX, true, true, false);
    ctx->save_for_backward({xq.qt, xq.scale, wq.qt, wq.scale});
    ctx->saved_data["w_dtype"] = static_cast<int64_t>(w.scalar_type());
    // y [m, out] = x [m, in] W^T; the second operand column-major, as _scaled_mm needs it.
    if (bias_in_product(x)) {
      return at::_scaled_mm(xq.q, wq.q.t(), xq.scale, wq.scale, b.to(x.scalar_type()), std::nullopt, x.scalar_type(), true);
    }
    return at::_scaled_mm(xq.q, wq.q.t(), xq.scale, wq.scale, std::nullopt, std::nullopt, x.scalar_type(), true) + b.to(x.scalar_type());
  }

  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx, torch::autograd::variable_list grads) {
    forget_last_input();
    auto saved = ctx->get_saved_variables();
    const auto &xqt = saved[0], &x_scale = saved[1], &wqt = saved[2], &w_scale = saved[3];
    const auto w_dtype = static_cast<at::ScalarType>(ctx->saved_data["w_dtype"].toInt());
    auto g = grads[0].contiguous();
    auto gq = quantize(g, at::kFloat8_e5m2, E5M2_MAX, true, true, true, true);
    auto gb = gq.sums.to(w_dtype);
    // dL/dx [m, in] = g [m, out] W [out, in] (W column-major: its transpose row-major);
    // dL/dW [out, in] = g^T [out, m] x [m, in] (x column-major: its transpose row-major).
    auto gx = at::_scaled_mm(gq.q, wqt.t(), gq.scale, w_scale, std::nullopt, std::nullopt, g.scalar_type(), false);
    auto gw = at::_scaled_mm(gq.qt, xqt.t(), gq.scale, x_scale, std::nullopt, std::nullopt, w_dtype, false);
    return {gx, gw, gb};
  }
};

thread_local std::string last_error;

}  // namespace

extern "C" {

void bwm_fp8_set_quantize_pass(QuantizePass pass) { quantize_pass = pass; }

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
