"""Is the drone any good: the random and scripted baselines (baselines.py), evaluation of any policy on a
batched env (evaluate.py), the competence protocol on unseen scenes (competence.py), and `navi run`,
the main job (main_job.py). `navi bench learn` and `navi bench train` live in navi_bench (benchmarks/).
"""
