"""navi_env: the drone environment over compiled .gmdag scenes, on CPU or CUDA.

Sub-packages, in the order data flows through them:
  corpus/   training corpora: folders of qualified .gmdag scenes (folder), spawn qualification (qualify),
            and the procedural default corpus built over the compiler workers' jobs (jobs)
  tracer/   the sphere tracer: scenes resident on a device (scene), the batched trace and point queries
            (trace; C++/CUDA in csrc/), their PyTorch twins (trace_ref), moving primitives (primitives),
            exact test scenes, accuracy checks and `navi bench trace`
  sim/      the simulation: SdfDagEnv (env) stepping physics, episodes, observation and rewards for N
            drones at once, scripted obstacles, the sensor's ray pattern, and `navi bench env`
  ecosystem/  the env for RL libraries: Gymnasium vector env (Navi/Explore-v0), TorchRL and skrl
            adapters, pictures, and `navi bench wrappers` (the libraries are optional extras)
service.py is the thin `navi serve env` shell over sim.env. docs/SIMULATION.md and docs/SDFDAG_RUNTIME.md
describe them; docs/ENVIRONMENT.md the adapters.
"""
