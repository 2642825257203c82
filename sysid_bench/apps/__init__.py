"""Layer 4 of sysid-bench (issue #37 §4): the commands people run (video, intercept, report, cli); nothing in the layers below imports it."""
