#include <ATen/Context.h>

extern "C" {

void bwm_sdp_set(bool flash, bool efficient, bool cudnn, bool math) {
  auto& ctx = at::globalContext();
  ctx.setSDPUseFlash(flash);
  ctx.setSDPUseMemEfficient(efficient);
  ctx.setSDPUseCuDNN(cudnn);
  ctx.setSDPUseMath(math);
}

void bwm_sdp_get(bool* flash, bool* efficient, bool* cudnn, bool* math) {
  auto& ctx = at::globalContext();
  *flash = ctx.userEnabledFlashSDP();
  *efficient = ctx.userEnabledMemEfficientSDP();
  *cudnn = ctx.userEnabledCuDNNSDP();
  *math = ctx.userEnabledMathSDP();
}

}
