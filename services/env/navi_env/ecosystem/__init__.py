"""Navi's batched drone environment for the RL ecosystem: Gymnasium, TorchRL, skrl and rsl_rl adapters
over navi_env.sim.env.SdfDagEnv that keep its tensors on its device.

batch.py     make_batched_env (a corpus folder -> SdfDagEnv writing two observation buffers in turn, so
             consecutive steps hand out distinct tensors without a copy), the observation bounds, and
             pool_view: the small view an MLP reads (MLP_VIEW, the nearest ray of each block)
gym.py       NaviVectorEnv (gymnasium.vector.VectorEnv, torch tensors, SAME_STEP autoreset),
             NumpyVectorEnv (host NumPy), NaviEnv (one drone, NumPy) and the id Navi/Explore-v0
render.py    pictures: a drone's spherical depth as a panorama, a top-down slice of its scene
torchrl.py   NaviTorchRLEnv, a torchrl EnvBase (TensorDict in and out, batch size N)
rows.py      copy_rows: the selected rows of a batch, one Triton kernel on CUDA (ended actors' final views)
skrl.py      SkrlEnv, skrl's torch Wrapper over NaviVectorEnv (flat pooled views)
rsl_rl.py    RslRlEnv, rsl_rl's VecEnv over NaviVectorEnv (observation groups, time_outs, logged metrics)

Importing this package registers Navi/Explore-v0 when Gymnasium is installed. The libraries are
optional extras (navi-env[gym], navi-env[torchrl], navi-env[skrl], navi-env[rsl_rl]); navi_env.sim and
navi_env.tracer import none of them. docs/ENVIRONMENT.md describes the adapters and how to train with each.
"""

from importlib.util import find_spec

if find_spec("gymnasium") is not None:
    from navi_env.ecosystem.gym import register_envs

    register_envs()
