"""Navi's benchmarks and the anchors they are measured against: what `navi bench` runs. The product
packages import nothing from here; only navi/commands/bench.py does (tests/test_layers.py checks both).

trace.py            `navi bench trace`: G rays/s of the tracer over placed agents, per scene or map set
warp.py, warp_kernel.py          the Warp BVH anchor (exact mesh rays, moving boxes put back per step)
nanovdb.py, nanovdb_kernel.py    the NanoVDB narrow-band anchor in Warp's volume API
device_check.py     one tracer check on a CUDA host: builds, checks accuracy, times 1k/4k/8k agents
env.py              `navi bench env`: env-steps/s and the time of each stage
ecosystem.py        `navi bench wrappers`: env-steps/s of the raw env and of each RL-library adapter
survey.py           `navi bench freespace`: free space, parts and reachable coverage per scene, timed
train.py            `navi bench train`: env, env + inference and env + training SPS, one or N ranks
learn.py, learn_rank.py          `navi bench learn`: time to competence on unseen scenes, seeds interleaved
"""
