"""The DAG stage: a signed lattice of distance samples -> a deduplicated sparse voxel octree (build.py),
with node keys hashed by MurmurHash3 (murmur.py).
"""
