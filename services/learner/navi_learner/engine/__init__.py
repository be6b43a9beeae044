"""The cognitive engine (CognitiveMambaPolicy in policy.py): RayViTEncoder (encoder.py) -> RND curiosity
(rnd.py) -> EpisodicMemory (memory.py, owned by the rollout) -> temporal core (temporal/: Mamba-2, its
plain reference, GRU) -> actor-critic heads (heads.py); moments pooled over data-parallel ranks
(moments.py). Shapes: N actors, T time, Az x El rays, D width.
"""
