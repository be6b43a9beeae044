// The C ABI of the launchers. trace_cpu.cpp and trace_cuda.cu implement the same launchers with
// the same signatures (suffix _cpu / _cuda); each returns 0 on success or an error code.
#pragma once

#include "launch_args.h"  // the argument structs

#ifdef _WIN32
#define NAVI_EXPORT __declspec(dllexport)
#else
#define NAVI_EXPORT __attribute__((visibility("default")))
#endif

extern "C" {
NAVI_EXPORT int navi_trace_cpu(const navi::TraceArgs* args);
NAVI_EXPORT int navi_sample_cpu(const navi::SampleArgs* args);
NAVI_EXPORT int navi_trace_cuda(const navi::TraceArgs* args);
NAVI_EXPORT int navi_sample_cuda(const navi::SampleArgs* args);
NAVI_EXPORT int navi_sweep_cpu(const navi::SweepArgs* args);
NAVI_EXPORT int navi_sweep_cuda(const navi::SweepArgs* args);
NAVI_EXPORT int navi_trace_args_size();
NAVI_EXPORT int navi_sample_args_size();
NAVI_EXPORT int navi_sweep_args_size();
NAVI_EXPORT int navi_origin_sample_size();
NAVI_EXPORT const char* navi_cuda_error_string(int code);
// The CUDA build's brick atlas (scene.py BrickAtlas): a 3-d texture of int8 samples, made and freed.
NAVI_EXPORT int navi_atlas_create_cuda(const int8_t* host, int64_t w, int64_t h, int64_t d, int device,
                                       uint64_t* tex_out, void** array_out);
NAVI_EXPORT int navi_atlas_destroy_cuda(uint64_t tex, void* array, int device);
}
