"""Navi wire contracts."""
