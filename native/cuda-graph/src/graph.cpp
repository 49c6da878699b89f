#ifdef BWM_CUDA
#include <ATen/cuda/CUDAGeneratorImpl.h>
#include <ATen/cuda/CUDAGraph.h>
#include <c10/cuda/CUDAFunctions.h>
#include <c10/cuda/CUDAStream.h>
#include <utility>
#include <vector>
// Only non-inline libtorch functions are called: c10/cuda/CUDAGuard.h and CUDAStream::synchronize
// are inline calls into cudart, which this library would then have to link and find at run time.
#endif
#include <exception>
#include <stdexcept>
#include <string>

#include "bwm_guarded.h"

#ifdef BWM_CUDA
namespace {
struct Recorder : at::cuda::CUDAGraph {
  // capture_end throws on a failed capture before it ends the capture of the RNG states
  // registered with the graph; they would count as capturing, and every later random number on
  // the device would fail ("Offset increment outside graph capture").
  void end_generator_captures() {
    for (auto& entry : captured_generator_states_) {
      entry.first->capturing_ = false;  // what capture_epilogue does, which libtorch does not export
    }
  }
};
}  // namespace
#endif

// A stream of libtorch's pool made current around work of its own (`CudaStream::scope`, and a
// graph's warm-up runs and capture); the streams and devices current before are kept for nested
// scopes.
struct BwmStream {
#ifdef BWM_CUDA
  explicit BwmStream(int device) : stream(c10::cuda::getStreamFromPool(false, static_cast<c10::DeviceIndex>(device))) {}
  c10::cuda::CUDAStream stream;
  std::vector<std::pair<c10::DeviceIndex, c10::cuda::CUDAStream>> before;

  void enter() {
    c10::DeviceIndex device = c10::cuda::current_device();
    c10::cuda::set_device(stream.device_index());
    before.emplace_back(device, c10::cuda::getCurrentCUDAStream(stream.device_index()));
    c10::cuda::setCurrentCUDAStream(stream);
  }

  // False when nothing was entered.
  bool leave() {
    if (before.empty()) {
      return false;
    }
    auto [device, previous] = before.back();
    before.pop_back();
    c10::cuda::setCurrentCUDAStream(previous);
    c10::cuda::set_device(device);
    return true;
  }
#endif
};

struct BwmGraph {
#ifdef BWM_CUDA
  explicit BwmGraph(int device) : stream(device) {}
  Recorder graph;
  // Captures cannot run on the default stream, so warm-up runs and the capture use this one.
  BwmStream stream;
#endif
};

#ifdef BWM_CUDA
namespace {
void make_current(BwmGraph* g) { g->stream.enter(); }

void restore(BwmGraph* g) { g->stream.leave(); }
}  // namespace
#endif

extern "C" {

const char* bwm_graph_error() { return last_error.c_str(); }

#ifdef BWM_CUDA

BwmGraph* bwm_graph_new(int device) {
  BwmGraph* g = nullptr;
  guarded([&] { g = new BwmGraph(device); });
  return g;
}

// Makes the graph's stream current once the work queued before is done.
bool bwm_graph_enter(BwmGraph* g) {
  return guarded([&] {
    c10::cuda::device_synchronize();
    make_current(g);
  });
}

// Waits for the graph's stream and makes the stream current before `enter` current again.
bool bwm_graph_leave(BwmGraph* g) {
  return guarded([&] {
    c10::cuda::device_synchronize();
    restore(g);
  });
}

bool bwm_graph_capture_begin(BwmGraph* g) {
  return guarded([&] {
    c10::cuda::device_synchronize();
    make_current(g);
    try {
      g->graph.capture_begin();
    } catch (...) {
      restore(g);
      throw;
    }
  });
}

bool bwm_graph_capture_end(BwmGraph* g) {
  bool ok = guarded([&] { g->graph.capture_end(); });
  restore(g);
  return ok;
}

// Ends a capture that failed part-way; the graph is unusable afterwards.
void bwm_graph_capture_abort(BwmGraph* g) {
  std::string why = last_error;
  guarded([&] { g->graph.capture_end(); });
  guarded([&] { g->graph.end_generator_captures(); });
  restore(g);
  last_error = why;
}

bool bwm_graph_replay(BwmGraph* g) {
  return guarded([&] { g->graph.replay(); });
}

void bwm_graph_free(BwmGraph* g) {
  guarded([&] { delete g; });
}

BwmStream* bwm_stream_new(int device) {
  BwmStream* s = nullptr;
  guarded([&] { s = new BwmStream(device); });
  return s;
}

bool bwm_stream_enter(BwmStream* s) {
  return guarded([&] { s->enter(); });
}

bool bwm_stream_leave(BwmStream* s) {
  return guarded([&] {
    if (!s->leave()) {
      throw std::runtime_error("leaving a CUDA stream that was not entered");
    }
  });
}

void bwm_stream_free(BwmStream* s) {
  guarded([&] { delete s; });
}

#else

BwmStream* bwm_stream_new(int) {
  last_error = "this build's libtorch has no CUDA (libtorch_cuda.so), so it has no CUDA streams";
  return nullptr;
}
bool bwm_stream_enter(BwmStream*) { return false; }
bool bwm_stream_leave(BwmStream*) { return false; }
void bwm_stream_free(BwmStream*) {}

BwmGraph* bwm_graph_new(int) {
  last_error = "this build's libtorch has no CUDA (libtorch_cuda.so), so it cannot record CUDA graphs";
  return nullptr;
}
bool bwm_graph_enter(BwmGraph*) { return false; }
bool bwm_graph_leave(BwmGraph*) { return false; }
bool bwm_graph_capture_begin(BwmGraph*) { return false; }
bool bwm_graph_capture_end(BwmGraph*) { return false; }
void bwm_graph_capture_abort(BwmGraph*) {}
bool bwm_graph_replay(BwmGraph*) { return false; }
void bwm_graph_free(BwmGraph*) {}

#endif
}
