"""navi_auditor."""
