"""The interception task (the paper's robot experiment, simulated): its scene and throws, the
policies, the evaluation and the figure, below the benchmark's experiment
(:mod:`sysid_bench.bench.interception`) and the ``sysid-bench intercept`` app
(:mod:`sysid_bench.apps.intercept`, whose docstring describes the task)."""
