"""navi_learner.serving."""
