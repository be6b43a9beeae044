"""navi_env."""
