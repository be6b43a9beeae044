"""navi_learner.evaluation."""
