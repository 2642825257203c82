"""sysid-bench: which method identifies a bouncing ball's physics from video, how well and how fast.

Modules
-------
physics    the simulator (NumPy, the one source of truth) and its JAX twin (``physics_jax``)
render     states to small videos, with optional nuisances
tracking   videos back to positions in metres
datasets   seeded, leak-free splits written to disk in chunks
estimator  Observation / Posterior / Forecast and the Estimator interface
metrics    pure functions scoring posteriors and forecasts
"""

__version__ = "0.1.0"
