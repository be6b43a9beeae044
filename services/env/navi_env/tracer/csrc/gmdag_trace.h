// The one traversal of a .gmdag scene corpus, compiled for the host (trace_cpu.cpp) and for the
// device (trace_cuda.cu). Every launcher calls trace_item / sample_point per ray / point; nothing
// about the algorithm lives anywhere else. docs/SDFDAG_RUNTIME.md describes it, docs/GMDAG.md the
// file, navi_env/tracer/scene.py the runtime layout built from it (leaf grid, corner-word bricks).
//
// Units inside: "voxel space" of the ray's scene, p_vox = (p_world - origin) / voxel_size, so the cube
// is [0, R]^3 and a unit direction stays a unit direction; t is in voxels until it is written out.
// The arithmetic is plain float32. The CPU build has no fused multiply-add (-ffp-contract=off) and
// takes bit-identical steps to trace_ref.py; where the device takes a cheaper route to the same value
// (floor through a rounding add, int8 to float through a byte permute) the result is exact, so that
// changes nothing. The CUDA build contracts a * b + c into fused multiply-adds (--fmad=true, ~3%
// faster), which moves positions and distances by an ulp: CUDA agrees with the CPU to a tolerance
// (docs/SDFDAG_RUNTIME.md, "Determinism"), not bit for bit.
//
// The traversal lives in headers by concern, each usable from host and device code alike (NAVI_HD);
// the launchers include this one, which includes them in dependency order:
//   trace_common.h  NAVI_HD, kBig and the float tricks, read-only loads, exact float helpers
//   launch_args.h   TraceArgs, SampleArgs, SweepArgs: the launchers' C ABI (mirrored in abi.py)
//   scene_record.h  scene records (SceneWord, Scene), lattice cells, the leaf grid and find_leaf
//   brick_sample.h  the field in a leaf: bricks (corner words or the atlas), far codes, walk_sample
//   primitives.h    dynamic primitives: distance, ray entry, culling, per-launch cone and mask tables
//   ray_walk.h      one ray: the origin sample, start_ray, the walk loop and far step, settle_hit
//   queries.h       per work item: trace_item, sample_point, sweep_item
#pragma once

#include "trace_common.h"
#include "launch_args.h"
#include "scene_record.h"
#include "brick_sample.h"
#include "primitives.h"
#include "ray_walk.h"
#include "queries.h"
