"""The drone simulation: N drones flying .gmdag scenes, stepped together on one device.

env.py           SdfDagEnv: reset and step, one stage after another (physics, trace, observation,
                 rewards, episodes), compiled into few kernels on CUDA
physics.py       body-frame velocity commands, the proximity speed limiter, contact-safe moves
observation.py   DistanceMatrix v2, the (N, 3, Az, El) observation, and the view statistics
rewards.py       the reward terms, each a small function of per-actor tensors
episodes.py      truncation, starvation, scene rotation and spawn selection as tensor ops
obstacles.py     scripted moving obstacles and squads of drones that see each other
goals.py         point-goal episodes: the goal bank, the goal draw at a spawn, path lengths, the goal mark
sensor.py, rng.py, adapters.py   range noise and dropout, counter-based random numbers, other
                 observation sources mapped to DistanceMatrix v2
"""
