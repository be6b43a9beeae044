"""The drone simulation: N drones flying .gmdag scenes, stepped together on one device.

env.py           SdfDagEnv: reset and step, one stage after another (physics, trace, observation,
                 rewards, episodes), optionally compiled into few kernels on CUDA
config.py        EnvConfig and its parts: every knob of the env in typed dataclasses
physics.py       body-frame velocity commands, the proximity speed limiter, contact-safe moves
observation.py   DistanceMatrix v2, the (N, 3, Az, El) observation, and the view statistics
rewards.py       the reward terms, each a small function of per-actor tensors
episodes.py      truncation, starvation, scene rotation and spawn selection as tensor ops
obstacles.py     scripted moving obstacles and squads of drones that see each other
sensor.py, rays.py, rng.py, adapters.py   the ray pattern and its noise, counter-based random numbers,
                 other observation sources mapped to DistanceMatrix v2
"""
