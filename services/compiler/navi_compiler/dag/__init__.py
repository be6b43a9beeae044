"""navi_compiler.dag."""
