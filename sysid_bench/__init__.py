"""sysid-bench: which method identifies a bouncing ball's physics from video, how well and how fast.

Modules
-------
physics    the simulator (NumPy, the one source of truth) and its JAX twin (``physics_jax``)
render     states to small videos, with optional nuisances
tracking   videos back to positions in metres
datasets   seeded, leak-free splits written to disk in chunks
estimator  Observation / Posterior / Forecast and the Estimator interface
spec       what a method declares about itself (MethodSpec), read by the harness
simulator  the counting, budgeted simulator and the likelihood simulation-based methods share
testing    check_estimator, the public contract check
metrics    pure functions scoring posteriors and forecasts
cli        the ``sysid-bench`` command line (also ``python -m sysid_bench``)
"""

__version__ = "0.1.0"
