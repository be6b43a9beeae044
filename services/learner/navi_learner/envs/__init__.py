"""navi_learner.envs."""
