"""The interception task: the paper's robot experiment, simulated and closed on forecasts.

A slow end effector must meet a bouncing ball whose physics it does not know, from a camera-like
video seen one frame at a time, with its model reset at every throw (paper, last experiment: a
PR2 caught 27 of 35 throws; random policies at 1 Hz and 2 Hz caught 8 and 10).

The scene (:class:`Scene`, every number an option of :func:`evaluate`)
-----------------------------------------------------------------------
* Each throw draws ``e, g, d, r`` from the test split's sub-ranges (``datasets.SUBRANGES_TEST``),
  a launch from ``physics.STATE0_RANGES`` and a floor height ``U(0, floor_offset)`` (1 m); the
  ball is simulated on that floor and filmed by the fixed camera framed on floor 0 (so one world
  frame serves ball, camera and effector), 100x50 (W x H) with the camera-like nuisances of the
  shipped Vid2Param ``camera`` checkpoint: motion blur 0.5, occlusion 0.05, dropped frames 0.05,
  pixel noise 8 grey levels.
* The effector moves only vertically on the line ``x = x_catch = 5 m``, within
  ``[0, 11] m`` (the box over the highest floor), starting at 3.5 m, at most ``speed = 1 m/s``.
* The throw is scored at the first crossing of ``x_catch`` by the ball's centre after
  ``t_min = 3 s``: it succeeds when the effector is within ``catch_radius = 0.5 m`` of the
  ball's centre then. Every launch of the ranges reaches the floor before 2.3 s, so the scored
  crossing always comes after at least one bounce (``n_bounces`` records it). Throws are
  redrawn when the ball does not cross in ``(t_min, t_max = 8 s]`` (it stopped short of the
  line) or moved less than ``min_swing = 1 m`` up and down in the second before the crossing
  (rolling or hopping low: nothing left to predict).
* Why the limit bites: by ``t_min`` the effector covers 3 m from its start, ``[0.5, 6.5] m``
  (``[0, 7] m`` with the catch radius), and one more metre per second after, while crossing
  heights are 0.04-6.8 m (200 throws, seed 0): the crossings are reachable by an effector that
  knows them at launch (``reachable``; the oracle catches them), but the ball moves vertically at
  up to ~13 m/s, so a controller that waits and follows what it sees (the ``react`` policy)
  arrives too late. Without the limit ``react`` catches nearly every throw: it is the limit,
  not the camera, that makes prediction necessary (figures in ``docs/intercept.md``).

The controller sees frame ``k`` at ``t = k dt`` (20 Hz), returns a target height, and the effector
heads for it at the speed limit until the next frame (no actuation delay; the control step's
wall time is measured and reported separately).

Policies (:func:`make_policy`)
------------------------------
``oracle``         knows the true crossing: the ceiling.
``random-1hz``, ``random-2hz``  a uniform random target in the effector's range every 1 s / 0.5 s.
``react``          "wait and react": the target is the height the ball is seen at now.
``kalman``         tracked positions, a constant-acceleration Kalman filter per axis with bounce
                   and wall detection, ballistic prediction with bounce reflection (the suite's
                   simulator with the filter's gravity, restitution and floor, no drag).
declared policies   an online method's stream (:class:`StreamPolicy`), as the method declares
                   them (``policies``): Vid2Param's ``vid2param`` and ``vid2param-physics``,
                   its camera checkpoint forecasting in latent space or through the physics.
any registered identifying method (``lsq``, ``nuts``, ...)  re-identifies on all frames so far
                   every ``every`` frames and forecasts with its ``forecast``.

Forecasting policies aim at the forecast mean's first crossing of ``x_catch`` after ``t_min``.

Modules, one concern each: :mod:`.scene` (the scene, the throws, crossing prediction),
:mod:`.policies` (the controller interface and the policies built on the suite's pieces),
:mod:`.kalman` (the Kalman policy), :mod:`.registry` (policy names), :mod:`.evaluation` (running
and scoring), :mod:`.results` (files, figure, report section), :mod:`.cli` (the command line).
"""

from __future__ import annotations

from sysid_bench.apps.intercept.cli import add_arguments, run
from sysid_bench.apps.intercept.results import write_results
from sysid_bench.bench.intercept.evaluation import evaluate, summarise, wilson_interval
from sysid_bench.bench.intercept.figure import intercept_figure
from sysid_bench.bench.intercept.kalman import Kalman
from sysid_bench.bench.intercept.policies import (
    Identify,
    Oracle,
    Policy,
    RandomTargets,
    React,
    StreamPolicy,
)
from sysid_bench.bench.intercept.registry import (  # noqa: F401 (_stream_policies: the report reads it)
    POLICIES,
    _stream_policies,
    known_policies,
    make_policy,
)
from sysid_bench.bench.intercept.scene import (
    CAMERA_NUISANCE,
    CATCH_RADIUS_MAX,
    Scene,
    Throw,
    crossing_from_forecast,
    make_throw,
)

__all__ = [
    "Scene",
    "Throw",
    "Policy",
    "Oracle",
    "RandomTargets",
    "React",
    "Kalman",
    "Identify",
    "StreamPolicy",
    "POLICIES",
    "known_policies",
    "make_policy",
    "make_throw",
    "evaluate",
    "summarise",
    "wilson_interval",
    "crossing_from_forecast",
    "write_results",
    "intercept_figure",
    "CAMERA_NUISANCE",
    "CATCH_RADIUS_MAX",
    "add_arguments",
    "run",
]

