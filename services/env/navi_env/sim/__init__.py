"""navi_env.sim."""
