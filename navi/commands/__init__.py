"""navi.commands."""
