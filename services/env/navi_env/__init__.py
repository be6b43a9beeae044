"""navi_env: the drone environment over compiled .gmdag scenes, on CPU or CUDA.

Layers, bottom to top; a module imports its own layer and those below it, never one above:
  config.py   EnvConfig and its parts: every knob of the env in typed dataclasses
  rays.py     the sensor's ray pattern in the body frame, the full-sphere pattern, the tiled ray order
  tracer/     the sphere tracer: scenes resident on a device (scene), the batched trace and point queries
              (trace; C++/CUDA in csrc/), their PyTorch twins (trace_ref), moving primitives (primitives),
              exact test scenes and accuracy checks
  space/      a scene's free space at the drone's radius (freespace), spawn qualification (qualify) and
              point-goal tables (goal_tables)
  sim/        the simulation: SdfDagEnv (env) stepping physics, episodes, observation and rewards for N
              drones at once, scripted obstacles, sensor noise, the per-step point-goal logic
  corpus/     training corpora: folders of qualified .gmdag scenes (folder) and the procedural default
              corpus built over the compiler workers' jobs (jobs)
  ecosystem/  the env for RL libraries: Gymnasium vector env (Navi/Explore-v0), TorchRL and skrl
              adapters, pictures (the libraries are optional extras)
  service.py  the thin `navi serve env` shell over sim.env
docs/SIMULATION.md and docs/SDFDAG_RUNTIME.md describe them; docs/ENVIRONMENT.md the adapters.
"""
