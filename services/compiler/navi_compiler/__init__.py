"""navi_compiler."""
