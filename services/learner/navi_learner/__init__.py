"""navi_learner: the cognitive engine and the PPO learner that trains it in-process with the env.

Sub-packages, bottom to top (a module imports only its own sub-package and those below it):
  config.py     the typed configuration all of them read
  engine/       the cognitive engine: RayViT encoder -> RND -> episodic memory -> temporal core -> heads
  envs/         what the learner trains against: the BatchedEnv protocol and the env capabilities it
                reads, the env factory, a toy env, and a remote env over Zenoh
  serving/      checkpoints, the model registry, the REST control plane, ONNX export
  ppo/          the algorithm: rollout storage, GAE, the PPO loss, the training loop and its learner,
                compiled policy steps, stage timers, promotion, data-parallel sync, episode statistics
                and the run folder
  evaluation/   baselines, evaluation, the competence protocol, the main job
  service/      the `navi serve learner` service: the tap on the training loop, its publishers, floor
                plans, bring-up, the training and inference loops, and the service shell
docs/ACTOR.md and docs/TRAINING.md describe them.
"""
