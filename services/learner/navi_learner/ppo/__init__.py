"""PPO, CleanRL-style: rollout storage (rollout.py) -> advantages (gae.py) -> the loss (loss.py) -> the
loop that runs them (train.py: collect -> learn -> report), over the run's learner, set up or resumed
before the first rollout and checkpointed (learner.py); the policy steps, eager or compiled (compile.py);
stage timers and the training clock (timing.py); promotion into the model registry (promotion.py);
data-parallel collectives and their single-process twin (dist.py), episode statistics on the device
(stats.py), and the run folder, logs and report (runs.py).
"""
