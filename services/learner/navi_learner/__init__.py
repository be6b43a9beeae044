"""navi_learner."""
