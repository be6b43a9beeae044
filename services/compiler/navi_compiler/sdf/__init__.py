"""The signed distance stage: grid.py places the scene in the power-of-two cube; sign.py decides which
lattice points are free; distance.py computes exact near-field distances and farfield.py a far-field
lower bound; reference.py runs them as the NumPy reference engine and torch_engine.py as the PyTorch one
(CPU or CUDA). The C++ core (csrc/) is the fast twin of each stage.
"""
