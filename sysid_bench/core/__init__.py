"""Layer 1 of sysid-bench (issue #37 §4): the physics, systems, rendering, tracking, the Estimator contract, metrics, datasets and their helpers; it imports nothing above it."""
