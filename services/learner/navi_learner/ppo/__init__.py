"""navi_learner.ppo."""
