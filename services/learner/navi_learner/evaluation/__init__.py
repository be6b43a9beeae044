"""Is the drone any good: the random and scripted baselines (baselines.py), evaluation of any policy on a
batched env (evaluate.py), the competence protocol on unseen scenes (competence.py), `navi bench learn`
(bench_learn.py), `navi bench train` (bench_train.py), and `navi run`, the main job (main_job.py).
"""
