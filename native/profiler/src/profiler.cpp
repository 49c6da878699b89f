#include <torch/csrc/autograd/profiler_kineto.h>

#include <exception>
#include <set>
#include <string>

#include "bwm_guarded.h"

extern "C" {
const char* bwm_profiler_last_error() { return last_error.c_str(); }

bool bwm_profiler_start(bool cuda) {
  return guarded([&] {
    using torch::profiler::impl::ActivityType;
    torch::profiler::impl::ProfilerConfig config(torch::profiler::impl::ProfilerState::KINETO);
    std::set<ActivityType> activities{ActivityType::CPU};
    if (cuda) activities.insert(ActivityType::CUDA);
    torch::autograd::profiler::prepareProfiler(config, activities);
    torch::autograd::profiler::enableProfiler(config, activities);
  });
}

// Stops the profiler; saves its trace at `path` unless it is null.
bool bwm_profiler_stop(const char* path) {
  return guarded([&] {
    auto result = torch::autograd::profiler::disableProfiler();
    if (path != nullptr) result->save(path);
  });
}
}
