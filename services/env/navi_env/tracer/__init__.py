"""navi_env.tracer."""
