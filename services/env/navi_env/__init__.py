"""navi_env: batched sphere tracing of .gmdag scenes (CPU and CUDA) and the drone environment.

Tracer modules: `scene` (SceneCorpus on a device), `trace` (trace, sample_distance), `trace_ref`
(PyTorch twins), `rays` (spherical pattern, tiled ray order), `cuda_build` (CUDA JIT),
`analytic_scenes` (exact test scenes), `bench_trace` / `device_check` (benchmarks).
See docs/SDFDAG_RUNTIME.md.
"""
