"""The sphere tracer: many .gmdag scenes resident on a device, and rays, points and sweeps traced through
them in one launch.

  scene.py         SceneCorpus: the runtime tree (leaf grid, bricks, far codes) built from .gmdag files
  trace.py         trace / sample_distance / sweep: validation, then one C++ (CPU threads) or CUDA launch
  trace_ref.py     the same algorithm in plain PyTorch, the slow twin every parity test compares with
  primitives.py    moving spheres, capsules and boxes traced in the same pass as the static scene
  abi.py           ctypes mirrors of the launch argument structs (csrc/launch_args.h)
  cuda_build.py    nvcc build of csrc/trace_cuda.cu on first use, cached
  csrc/            the traversal in headers shared by host and device, the thin .cpp and .cu launchers
  analytic_scenes.py, accuracy.py                  exact scenes and accuracy checks

`navi bench trace` and its anchors live in the navi_bench package (benchmarks/navi_bench).
"""
