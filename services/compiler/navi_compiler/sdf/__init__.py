"""navi_compiler.sdf."""
