"""navi_compiler: scenes -> .gmdag files, offline.

  ingest/     any source (meshes, Quake 3 .bsp/.pk3, procedural scenes) -> Scene (scene.py)
  sdf/        placement in the power-of-two cube, then the signed distance lattice: sign, exact near-field
              distance and far-field bound (NumPy reference stages; the C++ core in csrc/ and a PyTorch
              engine are their fast twins)
  dag/        the lattice -> a deduplicated sparse voxel DAG (build.py, MurmurHash3 keys in murmur.py)
  compile.py  the pipeline, Scene -> Gmdag
  gmdag.py    the .gmdag file format: reader, writer, validator; check.py describes files (`navi check`)
service.py is the thin `navi serve compiler` shell (compile workers and their client). docs/COMPILER.md
and docs/GMDAG.md describe them.
"""
