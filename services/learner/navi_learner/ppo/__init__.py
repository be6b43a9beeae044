"""PPO, CleanRL-style: rollout storage (rollout.py) -> advantages (gae.py) -> the loss (loss.py) -> the
loop that runs them (train.py: collect -> advantages -> update -> log -> checkpoint); data-parallel sync
(dist.py), episode statistics on the device (stats.py), and the run folder, logs and report (runs.py).
"""
