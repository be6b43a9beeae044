// pybind11 module navi_env.tracer._trace_cpu: forwards the address of a ctypes argument struct
// (navi_env/tracer/abi.py) to the CPU launchers. No logic lives here.
#include <pybind11/pybind11.h>

#include <cstdint>

#include "trace_launch.h"

PYBIND11_MODULE(_trace_cpu, m) {
  m.doc() = "CPU launchers of the .gmdag tracer (see navi_env.tracer.trace)";
  m.def(
      "trace", [](uintptr_t args) { return navi_trace_cpu(reinterpret_cast<const navi::TraceArgs*>(args)); },
      pybind11::call_guard<pybind11::gil_scoped_release>(), "Trace rays; args is the address of a TraceArgs.");
  m.def(
      "sample", [](uintptr_t args) { return navi_sample_cpu(reinterpret_cast<const navi::SampleArgs*>(args)); },
      pybind11::call_guard<pybind11::gil_scoped_release>(), "Sample the field; args is a SampleArgs address.");
  m.def(
      "sweep", [](uintptr_t args) { return navi_sweep_cpu(reinterpret_cast<const navi::SweepArgs*>(args)); },
      pybind11::call_guard<pybind11::gil_scoped_release>(), "Sweep obstacles; args is a SweepArgs address.");
  m.def("trace_args_size", &navi_trace_args_size, "sizeof(TraceArgs) in this build");
  m.def("sweep_args_size", &navi_sweep_args_size, "sizeof(SweepArgs) in this build");
  m.def("sample_args_size", &navi_sample_args_size, "sizeof(SampleArgs) in this build");
  m.def("origin_sample_size", &navi_origin_sample_size, "sizeof(OriginSample) in this build");
}
