"""navi_env.corpus."""
