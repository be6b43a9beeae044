"""navi_learner: the cognitive engine and the PPO learner that trains it in-process with the env.

Sub-packages, in the order a training step uses them:
  envs/         what the learner trains against: the BatchedEnv protocol, the env factory, a toy env,
                and a remote env over Zenoh
  engine/       the cognitive engine: RayViT encoder -> RND -> episodic memory -> temporal core -> heads
  ppo/          the algorithm: rollout storage, GAE, the PPO loss, the training loop, data-parallel sync,
                episode statistics and the run folder
  evaluation/   baselines, evaluation, the competence protocol, `navi bench learn|train`, the main job
  serving/      checkpoints, the model registry, the REST control plane, ONNX export
config.py holds the typed configuration all of them read; service.py is the thin `navi serve learner`
shell. docs/ACTOR.md and docs/TRAINING.md describe them.
"""
