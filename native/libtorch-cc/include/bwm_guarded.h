// The C++ shims' way of reporting errors across the C boundary: run a call, catch what it throws,
// keep the message for the Rust side to read (each shim exports an accessor for `last_error`).
#pragma once

#include <exception>
#include <string>

namespace {
thread_local std::string last_error;

template <class F>
bool guarded(F f) {
  try {
    f();
    return true;
  } catch (const std::exception& e) {
    last_error = e.what();
  } catch (...) {
    last_error = "unknown C++ exception";
  }
  return false;
}
}  // namespace
