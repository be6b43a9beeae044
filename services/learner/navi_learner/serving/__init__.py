"""Trained models out to the world: the checkpoint format (checkpoint.py), the model registry with aliases
and an audit log (registry.py), its REST control plane (control_plane.py), ONNX export (export.py), and
the reference checkpoints that ship with Navi (references.py).
"""
