"""navi_learner.engine."""
