"""NUTS (NumPyro) on the differentiable JAX simulator: the suite's reference posterior.

Model
-----
* **Likelihood** — exactly :func:`sysid_bench.core.simulator.gaussian_loglik`, written in JAX
  (:func:`loglik_jax`, tested equal): observed positions are the simulated ones plus independent
  N(0, ``sigma``^2) noise per coordinate, ``sigma`` **fixed** (hyperparameter, default
  ``sysid_bench.core.simulator.DEFAULT_SIGMA`` = 0.02 m; see there for why it is not inferred); unseen (NaN)
  frames contribute nothing.
* **Prior** — uniform on ``PRIOR`` for ``(e, g, d, r)``. Each parameter is sampled through the
  logit of its position in its range (an unconstrained space; the uniform prior there has
  density ``sigmoid(x) sigmoid(-x)``), so hard prior edges do not stop NUTS.
* **Initial state** — ``Observation.state0`` when given (held fixed). Otherwise it is *sampled*
  as a nuisance parameter, uniform on the box (``x0`` in [0, 10], ``y0`` in [floor, floor + 10])
  and on ``[-V0_MAX, V0_MAX]`` m/s for each velocity, starting from ``methods._tracks.prepare``'s
  estimate (refitted on the frames before the first contact when ``prepare`` extrapolated it
  back across one: :func:`methods._tracks.start_before_contact` (in ``prepare``),
  ``extras["state0_before_contact"]``). Sampling it makes the intervals honest about how well
  the start is known; holding the polynomial estimate fixed would bias ``e`` and ``g`` with no
  spread to show for it.
* **Floor** — ``Observation.floor`` when given (held fixed). Otherwise it is *sampled* as a
  nuisance parameter, as emcee samples it: uniform on ``FLOOR_BOX`` (20) standard errors
  (``Track.floor_std``) either side of ``methods._tracks.prepare``'s estimate (with a given
  initial state, no higher than its height), through the logit like the rest; a sampled
  initial state's height is then uniform on ``[floor, floor + 10]`` for its own floor. Every
  stage carries it: the search, the mode and Laplace covariance, the whitened NUTS coordinates
  and the forward-mode gradient (the JAX simulator's contact times depend on the floor
  differentiably). Held at the estimate instead, a floor 2 cm off put g 8 posterior widths from
  the truth on positions with 1 cm noise, with the model check passing. The draws' floors are
  summarised in ``extras["floor_mean"]``/``["floor_post_std"]`` (``floor_rhat``, ``floor_ess``,
  ``floor_box``); ``extras["floor"]``/``["floor_std"]`` stay the track's estimate and its
  standard error. ``Posterior.samples`` stay ``(e, g, d, r)``.

Gradients go through the JAX simulator including its contact times
(:mod:`sysid_bench.core.physics_jax`). They are computed in **forward mode** (one ``jvp`` per
sampled dimension, vectorised) behind a ``custom_jvp``: through a 200-frame ``lax.scan`` with
masked contact passes this is several times faster on a CPU than reverse mode, and reverse
mode (what NumPyro asks for) then only transposes a dot product.

How it runs
-----------
With ``sigma`` = 2 cm the log-likelihood spans 10^4-10^5 nats over the prior and has cliffs
where a bounce or the start of rolling comes and goes, so NUTS is not left to find the mode
alone:

1. a cross-entropy search on batched NumPy simulations (:func:`_search`: prior draws, then
   Gaussians fitted to the best 5%) finds the right basin;
2. L-BFGS (SciPy) from its best points, then Newton steps with a finite-difference Hessian of
   the exact gradient, give the mode and the Laplace covariance ``L L^T`` in logit coordinates;
3. NUTS (``numpyro.infer.hmc.hmc(..., algo="NUTS")`` with its windowed step-size and mass-matrix
   adaptation) samples ``z`` with ``x = x_mode + L z``: a roughly isotropic target, so trees
   stay shallow (about 5 leapfrog steps per iteration). The chain loop is one jitted
   ``lax.scan`` taking the observation as an argument, compiled once per (frame bucket, known
   or sampled initial state and floor, budgets) and reused — NumPyro's ``MCMC`` driver re-jits its loop
   for every run. Chains run one after another (the first from the mode, the others from
   ``z ~ N(0, 0.25 I)``).
4. A stuck chain stops: after :data:`PROBE_ITERATIONS` warm-up iterations, a mean tree size
   of at least :data:`STUCK_TREE` of the depth cap with a step size below :data:`STUCK_STEP`
   (a ball at rest, one frame repeated, an outlier frame the model cannot pass through: flat
   or ridged directions the Laplace whitening does not fit) skips every later iteration
   inside the compiled loop. Such a chain would spend ~10x a normal fit's leapfrog steps on
   draws that do not mix (the report's frozen-ball clip: 63 of 63 steps, R-hat 1.6, ~5x the
   CPU of a normal clip); the answer is then the Laplace approximation's draws with
   ``converged`` False, ``stopped_stuck`` True and ``warning`` saying so, and R-hat and ESS NaN.

Counting
--------
``extras["n_simulations"]`` counts trajectories as ``sysid_bench.core.simulator.CountingSimulator`` does (one
trajectory = one simulation): the search batches (``n_init`` per round), one per potential
evaluation of the optimiser, Newton steps and Hessian, one per leapfrog step (``num_steps``,
warm-up included) and one per chain for NumPyro's initial potential — each of these is one
trajectory with its gradient — and one for the fit check below.

Diagnostics
-----------
``extras`` holds split R-hat and ESS per parameter (``numpyro.diagnostics``; with one chain the
split halves still give R-hat), divergent transitions, mean tree size, step size, the RMS
residual of the mode's trajectory (``map_rms_m``) and ``converged``: R-hat < 1.05, ESS >= 50 for
e, g, d, fewer than 2% divergences and ``map_rms_m`` <= 3 sigma (a larger residual means a wrong
basin or a track the model cannot make). A run that fails these is returned, not raised:
``converged`` is False and ``warning`` says why.

Model check (``Posterior.check``, :meth:`methods._simulation.Fit.checked`): the posterior mean
simulated from the mean of the draws' initial states (and floors, when sampled) against the seen positions, judged against ``sigma``
(:meth:`sysid_bench.core.estimator.Check.from_residuals`). A failed check keeps the mean and widens
the intervals to what the data supports (:func:`methods._simulation.widen_to_support`: to hold
the best fit a local least-squares refinement from the mean finds, or to at least the prior's
when even that fit fails); its simulations are in ``extras["check_simulations"]``.

On the other systems
--------------------
NUTS on any registered system other than the ball (:meth:`NUTS._fit_points`, composing the
generic points likelihood of :mod:`methods._points`) samples through the system's JAX twin; a
system without one answers n/a (``NotImplementedError``).

The model is :mod:`methods._points`'s: the K tracked points are the twin's states seen
through the system's observation, plus independent Gaussian noise of a fixed ``sigma`` per
coordinate (default ``1.2 * system.noise_m``); a uniform prior on the prior box and, when
``Observation.state0`` is not given, on the initial-state box that ``state0_from_track`` gives
(intersected with the system's ``state_bounds``). NUTS samples the logits of the unit
coordinates (an unconstrained space; the uniform prior there has density
``sigmoid(x) sigmoid(-x)``).

How it runs, as on the ball (the same Laplace step):

1. the cross-entropy search and least-squares refinement of :mod:`methods._points` (batched
   NumPy simulations) find the basin;
2. L-BFGS and Newton steps on the JAX potential (exact gradients, forward mode through the
   twin) give the mode and the Laplace covariance ``L L^T`` in logit coordinates;
3. NumPyro's NUTS (windowed adaptation) samples ``z`` with ``x = x_mode + L z``, in jitted
   ``lax.scan`` blocks of ``num_warmup`` and ``num_samples`` iterations (one block when they
   are equal) compiled once per (system, frame bucket, known or sampled start, budgets) and
   reused across observations;
4. while split R-hat >= 1.05 or ESS < 50 on a parameter, every chain draws ``num_samples``
   more with its adapted kernel, at most ``max_extensions`` times: the diagnostics then judge
   all kept draws. The extension costs up to ``1 + max_extensions / 2`` times the sampling
   and only where the report's budget (150 + 150) left too few effective draws. Measured on
   10 test cases per system (``scripts/measure_systems.py --n 10``, 200 frames, 150 + 150,
   one thread, a loaded machine), R-hat < 1.05 and ESS >= 50 held in 4 -> 7 (spring),
   6 -> 9 (pendulum) and 4 -> 9 (collision) cases, at a median 5.3, 7.9 and 11.6 CPU s per
   identification (the first with its compile). What is left is the spring's curved ``w2``-
   ``k3`` ridge: in Laplace-whitened coordinates one direction's posterior variance there is
   48-377 (not 1) with kurtosis 5-10, so a hard case stays at ESS 10-50 of 450 draws (dense
   mass with 300 warm-up steps, probit instead of logit coordinates and no mass adaptation
   were each tried and did not help); such a run says so (``converged``, ``warning``).

The points seen through JAX: the system's ``jax_observe(states (T, S), theta (P,)) -> (T, K, 2)``
when it has one; else its NumPy ``_observe`` when that traces under JAX; else, when the
observation is an affine map of the state that does not depend on theta (checked numerically on
random states), that map; else the NumPy ``_observe`` through ``jax.pure_callback`` with
central-difference derivatives (any system; the slowest).

``extras``: split R-hat and ESS per parameter, divergences, mean tree size, step size,
``extensions`` (blocks drawn past ``num_samples``) and ``num_samples_kept``, the RMS
residual of the mode's trajectory (``map_rms_m``), ``converged`` (R-hat < 1.05 and ESS >= 50 on
every parameter, fewer than 2% divergences, ``map_rms_m`` <= 3 sigma) and ``warning``.
"""

from __future__ import annotations

from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from jax import lax
from numpyro.diagnostics import effective_sample_size, split_gelman_rubin
from numpyro.infer.hmc import hmc
from numpyro.infer.util import potential_energy
from scipy.optimize import minimize

from methods._points import (
    Points,
    PointsFit,
    SimulationOnSystems,
    _system,
    inflate,
    inflate_in_box,
    noise_inflation,
    refine,
    residual_inflation,
    search,
    sq_error,
)
from methods._simulation import Fit, Stopwatch, box_of, make_rng, track_residuals
from methods._tracks import clip_state
from sysid_bench.core import physics
from sysid_bench.core import physics_jax as pj
from sysid_bench.core._validate import check_positive_int
from sysid_bench.core.estimator import Observation, Posterior
from sysid_bench.core.physics import PRIOR_LO, PRIOR_SPAN
from sysid_bench.core.simulator import (
    CountingSimulator,
    check_sigma,
    gaussian_loglik,
    mean_sq_error,
)

__all__ = ["NUTS", "loglik_jax", "V0_MAX", "FLOOR_BOX", "jax_observer"]

#: Bound (m/s) of the uniform prior on each initial velocity when the initial state is sampled.
V0_MAX = 20.0
#: Half-width, in standard errors of ``methods._tracks.prepare``'s estimate, of the uniform prior
#: on an unknown floor (emcee's ``state0_box`` default, the same prior).
FLOOR_BOX = 20.0
_LO = jnp.asarray(PRIOR_LO)
_SPAN = jnp.asarray(PRIOR_SPAN)
_EPS = 1e-6  # keeps initial values off the unit interval's ends, where the logit is infinite


# ------------------------------------------------------------------------------------------
# likelihood (JAX mirror of sysid_bench.core.simulator.gaussian_loglik) with forward-mode gradients
def loglik_jax(sim_pos, obs_pos, mask, sigma):
    """``sysid_bench.core.simulator.gaussian_loglik`` in JAX.

    Parameters
    ----------
    sim_pos : array, shape (..., T, 2)
    obs_pos : array, shape (T, 2)
        NaN allowed where ``mask`` is False.
    mask : array of bool, shape (T,)
    sigma : float

    Returns
    -------
    array, shape (...)
    """
    n = 2.0 * jnp.count_nonzero(mask)
    m = mask[:, None]
    diff = jnp.where(m, sim_pos - jnp.where(m, obs_pos, 0.0), 0.0)
    sse = jnp.sum(diff * diff, axis=(-2, -1))
    return -0.5 * sse / sigma**2 - n * jnp.log(sigma) - 0.5 * n * jnp.log(2.0 * jnp.pi)


def _loglik_value(theta, state0, data, n_frames, dt):
    """Log-likelihood of one ball (theta (4,), state0 (4,)); -inf if the simulator gave up."""
    obs_pos, mask, floor, sigma = data
    states, bad = pj.simulate_core(theta[None], state0[None], floor[None], n_frames=n_frames, dt=dt)
    ll = loglik_jax(states[0, :, :2], obs_pos, mask, sigma)
    return jnp.where(bad[0], -jnp.inf, ll)


@partial(jax.custom_jvp, nondiff_argnums=(3, 4, 5, 6))
def _loglik(theta, state0, data, n_frames, dt, free_state, free_floor=False):
    """Log-likelihood of theta (4,) and state0 (4,); its derivative is taken in forward mode.

    ``data`` = ``(obs_pos, mask, floor, sigma)`` is treated as a constant (its tangent is
    ignored) except for the floor (a scalar) when ``free_floor``; ``state0`` is differentiated
    only when ``free_state``.
    """
    return _loglik_value(theta, state0, data, n_frames, dt)


@_loglik.defjvp
def _loglik_jvp(n_frames, dt, free_state, free_floor, primals, tangents):
    theta, state0, data = primals
    d_theta, d_state0, d_data = tangents
    if free_floor:
        # the floor rides at the end of x; the simulator's contact times carry its derivative
        obs_pos, mask, floor, sigma = data
        parts, dparts = [theta], [d_theta]
        if free_state:
            parts.append(state0)
            dparts.append(d_state0)
        x = jnp.concatenate(parts + [jnp.reshape(floor, (1,))])
        dx = jnp.concatenate(dparts + [jnp.reshape(d_data[2], (1,))])

        def f(x):
            s0 = x[4:8] if free_state else state0
            return _loglik_value(x[:4], s0, (obs_pos, mask, x[-1], sigma), n_frames, dt)
    elif free_state:
        x = jnp.concatenate((theta, state0))
        f = lambda x: _loglik_value(x[:4], x[4:], data, n_frames, dt)  # noqa: E731
        dx = jnp.concatenate((d_theta, d_state0))
    else:
        x = theta
        f = lambda x: _loglik_value(x, state0, data, n_frames, dt)  # noqa: E731
        dx = d_theta
    # every directional derivative in one vectorised forward pass (the gradient), then contract:
    # linear in the tangents, so reverse mode transposes this and never differentiates the scan
    val, grad = jax.vmap(lambda t: jax.jvp(f, (x,), (t,)), out_axes=(None, 0))(jnp.eye(x.size))
    return val, jnp.dot(grad, dx)


# ------------------------------------------------------------------------------------------
# the NumPyro model, in coordinates whitened by the Laplace approximation
def _dim(free_state, free_floor):
    """Sampled coordinates: e, g, d, r, then the initial state (4) and the floor (1) if free."""
    return 4 + 4 * bool(free_state) + bool(free_floor)


def _state_box(floor):
    """Lower corner and size of the initial-state prior box, arrays (4,) (``floor`` a scalar)
    or (..., 4) (``floor`` an array (...), one box per sampled floor)."""
    if jnp.ndim(floor):
        fl = jnp.asarray(floor, jnp.float64)
        lo = jnp.stack([jnp.zeros_like(fl), fl, jnp.full_like(fl, -V0_MAX), jnp.full_like(fl, -V0_MAX)], -1)
    else:
        lo = jnp.stack([0.0, jnp.asarray(floor, jnp.float64), -V0_MAX, -V0_MAX])
    span = jnp.array([physics.BOX_WIDTH, physics.BOX_WIDTH, 2 * V0_MAX, 2 * V0_MAX])
    return lo, span


def _physical(x, floor, s0_fixed, free_state, free_floor=False, box=None):
    """Unconstrained (logit) coordinates x (..., D) -> theta (..., 4), state0 (..., 4), floor.

    ``floor`` is the floor (a scalar) when it is known, else ``[lo, span]`` (2,) of its prior
    interval, and the floor is ``lo + span * sigmoid(x[..., -1])``, shape (...). A sampled
    initial state's height is uniform on ``[floor, floor + BOX_WIDTH]`` for its own floor.
    ``box``: ``(lo, span)`` (4,) each, the user's parameter box (a held parameter's span 0);
    None: the prior's.
    """
    u = jax.nn.sigmoid(x)
    lo, span = (_LO, _SPAN) if box is None else box
    theta = lo + span * u[..., :4]
    if free_floor:
        floor = floor[0] + floor[1] * u[..., -1]
    if free_state:
        lo, span = _state_box(floor)
        return theta, lo + span * u[..., 4:8], floor
    return theta, jnp.broadcast_to(s0_fixed, theta.shape), floor


def _model(data, *, n_frames, dt, free_state, free_floor=False):
    """Uniform prior on PRIOR (and on the state box when free), Gaussian position noise.

    The sampled site ``z`` (D,) has a flat base measure; ``x = x_ref + L z`` are the logit
    coordinates of the prior's unit intervals, and the prior density of uniform ``u`` in logit
    coordinates, ``sigmoid(x) sigmoid(-x)``, enters with the likelihood. ``x_ref`` and ``L`` are
    data (the Laplace mode and Cholesky factor of its covariance), so NUTS sees a roughly
    isotropic target and one compiled sampler serves every observation of a given length.
    """
    obs_pos, mask, floor, sigma, s0_fixed, x_ref, chol = data[:7]
    box = data[7] if len(data) > 7 else None  # the user's (lo, span); absent: the prior's
    D = _dim(free_state, free_floor)
    z = numpyro.sample("z", dist.ImproperUniform(dist.constraints.real_vector, (), event_shape=(D,)))
    x = x_ref + chol @ z
    log_prior = jnp.sum(jax.nn.log_sigmoid(x) + jax.nn.log_sigmoid(-x))
    theta, state0, fl = _physical(x, floor, s0_fixed, free_state, free_floor, box)
    ll = _loglik(theta, state0, (obs_pos, mask, fl, sigma), n_frames, dt, free_state, free_floor)
    numpyro.factor("log_post", ll + log_prior)


def _potential(z, data, *, n_frames, dt, free_state, free_floor=False):
    """NumPyro's potential energy (minus log posterior density) of the model at ``z`` (D,)."""
    model = partial(_model, n_frames=n_frames, dt=dt, free_state=free_state, free_floor=free_floor)
    return potential_energy(model, (data,), {}, {"z": z})


@lru_cache(maxsize=16)
def _compiled(n_frames, dt, free_state, num_warmup, num_samples, dense_mass, target_accept, max_tree_depth,
              free_floor=False):
    """Jitted potential (value, gradient) and one jitted NUTS chain for a configuration.

    NumPyro's ``hmc(potential_fn_gen=..., algo="NUTS")`` kernel does the sampling and the
    windowed step-size / mass-matrix adaptation; the loop over iterations is a ``lax.scan``
    here, with the observation as an argument, so every identification of the same (bucketed)
    length reuses one compiled chain instead of recompiling (``MCMC`` re-jits its loop per run).
    """
    pe = partial(_potential, n_frames=n_frames, dt=dt, free_state=free_state, free_floor=free_floor)
    init_kernel, sample_kernel = hmc(potential_fn_gen=lambda data: partial(pe, data=data), algo="NUTS")

    @jax.jit
    def chain(rng_key, z0, data):
        state = init_kernel(
            z0,
            num_warmup,
            dense_mass=dense_mass,
            target_accept_prob=target_accept,
            max_tree_depth=max_tree_depth,
            model_args=(data,),
            rng_key=rng_key,
        )

        def step(state):
            return sample_kernel(state, model_args=(data,))

        def body(carry, i):
            state, n_steps, stuck = carry
            # judged once, after the first PROBE_ITERATIONS: trees at the depth cap and a
            # collapsed step size mean the chain cannot move; every later iteration is skipped
            stuck = stuck | ((i == n_head) & (n_steps >= STUCK_TREE * cap * n_head)
                             & (state.adapt_state.step_size < STUCK_STEP))
            state = lax.cond(stuck, lambda s: s, step, state)
            n_steps = n_steps + jnp.where(i < n_head, state.num_steps, 0)
            return (state, n_steps, stuck), (state.z, state.num_steps, state.diverging)

        carry = (state, jnp.zeros((), state.num_steps.dtype), jnp.zeros((), bool))
        (state, _, stuck), (zs, steps, div) = lax.scan(
            body, carry, jnp.arange(num_warmup + num_samples))
        return zs[num_warmup:], steps, div[num_warmup:], state.adapt_state.step_size, stuck

    n_head = _probe_length(num_warmup)
    cap = 2 ** max_tree_depth - 1
    return jax.jit(jax.value_and_grad(pe)), chain


#: warm-up iterations a chain runs before :class:`NUTS` judges whether it is stuck; it is
#: when its mean tree size there is at least STUCK_TREE of the depth cap's leapfrog steps and
#: its adapted step size (whitened coordinates: ~0.3-1 on a posterior near its Laplace
#: approximation) has fallen below STUCK_STEP
PROBE_ITERATIONS = 50
STUCK_TREE = 0.75
STUCK_STEP = 0.1


def _probe_length(num_warmup: int) -> int:
    """Iterations a chain runs before it is judged stuck (:data:`PROBE_ITERATIONS`)."""
    return min(PROBE_ITERATIONS, num_warmup)


def _bucket(n, size):
    """Frames simulated for an observation of ``n`` frames: rounded up to a multiple of ``size``
    so prefixes of different lengths share a handful of compiled samplers."""
    return int(-(-n // size) * size)


class _Potential:
    """Potential energy and gradient in plain logit coordinates x (D,), counting evaluations."""

    def __init__(self, pe_vg, data_base, D, extra=()):
        self.pe_vg, self.base, self.D, self.n = pe_vg, data_base, D, 0
        self._data = data_base + (jnp.zeros(D), jnp.eye(D)) + tuple(extra)

    def __call__(self, x):
        self.n += 1
        val, grad = self.pe_vg(jnp.asarray(x, jnp.float64), self._data)
        val, grad = float(val), np.asarray(grad, dtype=np.float64)
        if not np.isfinite(val) or not np.isfinite(grad).all():
            return np.inf, np.zeros(self.D)
        return val, grad

    def hessian(self, x, scale):
        """Central differences of the exact gradient, steps ``1e-3 * scale`` (D,); symmetrised."""
        D = self.D
        H = np.empty((D, D))
        for i in range(D):
            h = 1e-3 * scale[i]
            e = np.zeros(D)
            e[i] = h
            H[i] = (self(x + e)[1] - self(x - e)[1]) / (2.0 * h)
        return 0.5 * (H + H.T)


def _laplace(pot, starts, *, maxiter_lbfgs=300, newton_iters=6):
    """Mode and covariance of the posterior in logit coordinates.

    L-BFGS-B from each of ``starts`` (keeping the lowest potential), then damped Newton steps
    with a finite-difference Hessian of the exact gradient (L-BFGS stalls early on a target
    whose curvatures span 1e0-1e8). Returns ``(x_map, cov, info)``; ``cov`` is made positive
    definite by clipping eigenvalues.
    """
    best = None
    for x0 in starts:
        opt = minimize(pot, x0, jac=True, method="L-BFGS-B", options={"maxiter": maxiter_lbfgs})
        if best is None or opt.fun < best.fun:
            best = opt
    opt = best
    x, f = np.asarray(opt.x, dtype=np.float64), float(opt.fun)
    scale = np.full(x.size, 1e-2)
    n_newton = 0
    for _ in range(newton_iters):
        H = pot.hessian(x, scale)
        w, V = np.linalg.eigh(H)
        w = np.maximum(w, 1e-8 * max(w.max(), 1e-8) + 1e-6)
        cov = (V / w) @ V.T
        scale = np.sqrt(np.diag(cov))
        g = pot(x)[1]
        step = -cov @ g
        t, improved = 1.0, False
        for _ in range(8):
            fn, _ = pot(x + t * step)
            if fn < f:
                improved = True
                break
            t *= 0.5
        n_newton += 1
        if not improved:
            break
        x, f_old, f = x + t * step, f, fn
        if f_old - f < 1e-6:
            break
    H = pot.hessian(x, scale)
    w, V = np.linalg.eigh(H)
    n_neg = int((w <= 0).sum())
    w = np.maximum(w, 1e-8 * max(w.max(), 1e-8) + 1e-6)
    cov = (V / w) @ V.T
    return x, cov, {"map_potential": f, "n_newton": n_newton, "hessian_nonpd": n_neg, "lbfgs_iters": int(opt.nit)}


def _search(sim, track, sigma, free, rng, n, rounds, n_starts, floor_box=None):
    """Cross-entropy search for starting points, on batched NumPy simulations.

    Round 0 draws ``n`` parameter vectors from the prior with the initial state (and an unknown
    floor) at its estimate (as ``lsq``); each later round draws ``n`` from a Gaussian fitted to
    the best 5% seen so far (the initial state and floor included when they are sampled,
    starting from their estimates' standard errors). The likelihood has cliffs where a bounce
    or the start of rolling comes and goes, so a gradient method started from a prior draw can
    stall on the wrong side of one; this search narrows in on the right basin first.

    ``floor_box`` : ``(lo, span)`` of the sampled floor's prior interval; None: the floor is
    ``track.floor``, fixed.

    Returns
    -------
    starts : list of ndarray, shape (D,)
        Up to ``n_starts`` best distinct points, logit coordinates, best first.
    info : dict
    """
    T, dt, floor = track.n_frames, track.dt, track.floor
    free_floor = floor_box is not None
    D = _dim(free, free_floor)
    lo_s, span_s = (np.asarray(a) for a in _state_box(floor))
    u_s0 = np.clip((track.state0 - lo_s) / span_s, _EPS, 1 - _EPS)
    v = np.empty((n, D))
    v[:, :4] = rng.random((n, 4))
    if free:
        v[:, 4:8] = u_s0
    if free_floor:
        v[:, -1] = np.clip((floor - floor_box[0]) / floor_box[1], _EPS, 1 - _EPS)
    pool_v, pool_ll = np.empty((0, D)), np.empty(0)
    n_elite = max(10, n // 20)
    box = box_of(track)  # the prior's, or the user's ranges and held values
    for r in range(rounds):
        theta = box.lo + box.span * v[:, :4]
        state = lo_s + span_s * v[:, 4:8] if free else np.repeat(track.state0[None], n, 0)
        fl = floor
        if free_floor:
            fl = floor_box[0] + floor_box[1] * v[:, -1]
            if free:  # the state's height is uniform above its own floor
                state[:, 1] += fl - floor
        pos = sim.positions(theta, clip_state(state, fl), T, dt, fl)
        ll = gaussian_loglik(pos, track.positions, track.mask, sigma)
        pool_v, pool_ll = np.concatenate((pool_v, v)), np.concatenate((pool_ll, ll))
        if r == rounds - 1:
            break
        elite = pool_v[np.argsort(-pool_ll)[:n_elite]]
        cov = np.cov(elite.T) + np.diag(np.full(D, 1e-12))
        if (free or free_floor) and r == 0:  # they did not vary yet: start from their errors
            cov[4:, :] = cov[:, 4:] = 0.0
            if free:
                cov[4:8, 4:8] = np.diag((np.maximum(track.state0_std, 1e-3) / span_s) ** 2)
            if free_floor:
                cov[-1, -1] = (track.floor_std / floor_box[1]) ** 2
        v = np.clip(rng.multivariate_normal(elite.mean(0), cov, size=n, method="eigh"), _EPS, 1 - _EPS)
    order = np.argsort(-pool_ll)
    starts = []
    for i in order:
        if len(starts) == n_starts:
            break
        if all(np.abs(pool_v[i] - pool_v[j]).max() > 1e-9 for j in starts):
            starts.append(i)
    return [_logit(pool_v[i]) for i in starts], {"search_best_loglik": float(pool_ll[order[0]])}


class NUTS(SimulationOnSystems):
    """NumPyro's No-U-Turn sampler on the JAX simulator (the ball) or on a system's JAX twin
    (any other registered system that has one, :meth:`NUTS._fit_points`; one without is n/a:
    ``NotImplementedError``).

    Parameters
    ----------
    system : str
        A registered system (:func:`sysid_bench.core.systems.available`).
    num_warmup : int
        Warm-up (step size and mass matrix adaptation) iterations per chain.
    num_samples : int
        Kept iterations per chain.
    num_chains : int
        Chains, run one after another (``chain_method="sequential"``: vectorised chains would
        lose the simulator's skip of contact-free frames, and the machine has 2 cores).
    sigma : float, optional
        Position noise standard deviation (m) of the likelihood, fixed; None:
        ``DEFAULT_SIGMA`` on the ball, the system's :func:`methods._points.default_sigma`
        elsewhere.
    n_init : int, optional
        Simulations per round of the starting-point search (another system: of the whole
        search); None: 1000 on the ball, 2000 elsewhere.
    search_rounds : int
        Rounds of that cross-entropy search (the first draws from the prior).
    n_starts : int, optional
        Best search points each refined by L-BFGS; the lowest potential wins. None: 3 on the
        ball, 5 elsewhere (see :func:`_fit_on_points`).
    max_opt_evals : int
        Another system only: residual evaluations of the least-squares refinement of each start.
    max_extensions : int
        Another system only: blocks of ``num_samples`` more draws an unconverged chain may add.
    dense_mass : bool
        Adapt a dense mass matrix in the whitened coordinates (diagonal by default: the Laplace
        whitening already removes the correlations).
    target_accept : float
        NUTS target acceptance probability.
    max_tree_depth : int
        Cap of the trajectory doubling (at most ``2**max_tree_depth - 1`` leapfrog steps).
    n_forecast : int
        Posterior samples simulated by ``forecast``.
    known : dict of str -> float, optional
        Another system only: parameters held fixed (a constant in the model: the problem maps
        their coordinate onto the value, so every draw holds it; mean the value, std 0);
        checked as ``--known`` is (:func:`sysid_bench.core.footage.parse_known`).
    prior : dict of str -> (float, float), optional
        Another system only: ranges replacing the system's uniform prior for these parameters
        (:func:`sysid_bench.core.footage.parse_prior`).
    frame_bucket : int
        Observations are padded (with unseen frames) to a multiple of this many frames, so that
        prefixes of different lengths share one compiled sampler per multiple. Compiling costs
        about half a minute per (length, known/unknown initial state) the first time.
    seed : int
    """

    name = "nuts"
    input_kind = "positions"
    min_frames = 3  # fewer seen frames cannot fix a state and parameters (``methods._tracks.prepare``)
    forecasts = True
    cost = 50
    #: the posterior calibration compares every other method with
    reference_posterior = True
    #: its fit (``_fit``/``_fit_points``) is a pure function of its hyperparameters and the
    #: observation: the search and the chains are seeded from ``seed`` per call (NumPy and a
    #: JAX key), the compiled samplers it keeps per process are a cache of code, not of data,
    #: and a fit in another process (JAX's persistent compilation cache or not) has the same
    #: bytes (``tests/test_fitcache.py``); section 0 reads calibration's reference posteriors
    #: (:mod:`sysid_bench.bench.fitcache`)
    pure_fit = True
    # ~25 s per posterior (~100 under load): where it is the reference (calibration, systems)
    # and, for its coverage off our physics, 3 of the MuJoCo videos (issue 29)
    scale_cases = {
        "smoke": {"identification": 0, "forecasting": 0, "changing": 0, "calibration": 1,
                  "foreign": 0, "systems": 1, "camera": 0},
        "default": {"identification": 0, "forecasting": 0, "changing": 0, "calibration": 3,
                    "foreign": 3, "systems": 3, "camera": 1},
        # the first look has no time for a sampler's compilation (1-3 min a system under load):
        # the reference posterior is the default run's
        "quick": 0,
    }
    scale_options = {
        "smoke": {"num_warmup": 30, "num_samples": 30, "n_init": 200},
        "default": {"num_warmup": 150, "num_samples": 150},
    }
    #: cheap budgets for check_estimator (same code path; one frame bucket for every prefix)
    contract_options = {
        "num_warmup": 40,
        "num_samples": 40,
        "n_init": 100,
        "search_rounds": 2,
        "n_starts": 1,
        "n_forecast": 20,
        "frame_bucket": 100,
    }

    per_system_defaults = {"n_init": (1000, 2000), "n_starts": (3, 5)}

    def __init__(
        self,
        *,
        system: str = "ball",
        num_warmup: int = 200,
        num_samples: int = 300,
        num_chains: int = 1,
        sigma: float | None = None,
        n_init: int | None = None,
        search_rounds: int = 4,
        n_starts: int | None = None,
        max_opt_evals: int = 100,
        dense_mass: bool = False,
        target_accept: float = 0.85,
        max_tree_depth: int = 6,
        n_forecast: int = 200,
        frame_bucket: int = 50,
        max_extensions: int = 2,
        known: dict | None = None,
        prior: dict | None = None,
        seed: int = 0,
    ):
        self.system = system
        self.num_warmup = num_warmup
        self.num_samples = num_samples
        self.num_chains = num_chains
        self.sigma = sigma
        self.n_init = n_init
        self.search_rounds = search_rounds
        self.n_starts = n_starts
        self.max_opt_evals = max_opt_evals
        self.dense_mass = dense_mass
        self.target_accept = target_accept
        self.max_tree_depth = max_tree_depth
        self.n_forecast = n_forecast
        self.frame_bucket = frame_bucket
        self.max_extensions = max_extensions
        self.known = known
        self.prior = prior
        self.seed = seed

    def _validate(self) -> None:
        super()._validate()
        self._check()

    # --------------------------------------------------------------------------------------
    def _check(self):
        for k in (
            "num_warmup", "num_samples", "num_chains", "n_init", "search_rounds", "n_starts",
            "max_opt_evals", "max_tree_depth", "n_forecast", "frame_bucket",
        ):
            check_positive_int(self._hp(k), k)
        check_positive_int(self.max_extensions, "max_extensions", minimum=0)
        sigma = check_sigma(self._sigma())
        try:
            ta = float(self.target_accept)
        except (TypeError, ValueError):
            ta = np.nan
        if not 0.0 < ta < 1.0:
            raise ValueError(f"target_accept: expected a probability in (0, 1), got {self.target_accept!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)):
            raise ValueError(f"seed: expected an int, got {self.seed!r}")
        return sigma

    def _fit(self, obs: Observation) -> Fit:
        """Posterior samples of ``(e, g, d, r)`` (see the module docstring); a forecast continues
        ``n_forecast`` of them (their parameters and, when sampled, their initial states) past
        the last frame. ``extras["n_simulations"]`` of a forecast counts the fit's too."""
        sw = Stopwatch()
        sigma = self._check()
        # a start extrapolated back across an early contact is refitted on the frames before
        # it (``prepare``: ``start_before_contact``); the search starts there
        track = self._prepare(obs)  # with the user's knowledge, if any, as its box
        sim = CountingSimulator()
        T, dt, floor = track.n_frames, track.dt, track.floor
        Tb = _bucket(T, int(self.frame_bucket))
        free = not track.state0_known
        free_floor = not track.floor_known
        D = _dim(free, free_floor)
        rng = make_rng(self.seed, 0)
        floor_box = None
        if free_floor:
            # flat on FLOOR_BOX standard errors either side of the estimate, as emcee's; with a
            # known start, no floor above the ball's starting height
            fl_lo, fl_hi = floor - FLOOR_BOX * track.floor_std, floor + FLOOR_BOX * track.floor_std
            if not free:
                fl_hi = min(fl_hi, float(track.state0[1]))
            floor_box = (fl_lo, fl_hi - fl_lo)

        # data, padded to the bucket length (padded frames are unseen)
        obs_pos = np.zeros((Tb, 2))
        mask = np.zeros(Tb, bool)
        obs_pos[:T] = np.where(track.mask[:, None], track.positions, 0.0)
        mask[:T] = track.mask
        s0_est = np.asarray(track.state0, dtype=np.float64)
        base = (
            jnp.asarray(obs_pos),
            jnp.asarray(mask),
            jnp.asarray(floor_box if free_floor else floor, jnp.float64),
            jnp.asarray(sigma, jnp.float64),
            jnp.asarray(s0_est),
        )

        # 1. global: cross-entropy search with batched NumPy simulations (starts as lsq does)
        starts, search_info = _search(
            sim, track, sigma, free, rng, int(self._hp("n_init")), int(self.search_rounds),
            int(self._hp("n_starts")),
            floor_box,
        )

        # 2. local: the mode and curvature (Laplace) of the model's potential
        pe_vg, chain = _compiled(
            Tb, dt, free, int(self.num_warmup), int(self.num_samples),
            bool(self.dense_mass), float(self.target_accept), int(self.max_tree_depth), free_floor,
        )
        # the user's knowledge: the parameter box as data after the whitening (one compiled
        # sampler for every box; without it the data and the compiled model are as they were)
        box = None if track.box is None else (jnp.asarray(track.box.lo),
                                              jnp.asarray(track.box.span))
        extra = () if box is None else (box,)
        pot = _Potential(pe_vg, base, D, extra)
        x_map, cov, lap_info = _laplace(pot, starts)
        sim.n_simulations += pot.n
        chol = np.linalg.cholesky(cov)

        # 3. NUTS in the whitened coordinates z (x = x_map + chol z), chains started near z = 0
        nc = int(self.num_chains)
        data = base + (jnp.asarray(x_map), jnp.asarray(chol)) + extra
        keys = jax.random.split(jax.random.PRNGKey(int(self.seed)), nc)
        zs, steps, divs, step_sizes = [], [], [], []
        stuck = None
        n_head = _probe_length(int(self.num_warmup))
        for c in range(nc):
            z0 = np.zeros(D) if c == 0 else 0.5 * rng.standard_normal(D)  # ~half a posterior sd
            zc, st, dv, ss, halted = chain(keys[c], jnp.asarray(z0), data)
            if bool(halted):
                # trees at the depth cap with a collapsed step size: this chain (and any
                # other) would spend ~10x a normal fit's leapfrog steps without mixing
                stuck = (float(np.asarray(st)[:n_head].mean()), float(ss))
                sim.n_simulations += int(np.asarray(st)[:n_head].sum()) + c + 1
                break
            zs.append(np.asarray(zc))
            steps.append(np.asarray(st))
            divs.append(np.asarray(dv))
            step_sizes.append(float(ss))
        if stuck is not None:
            # the Laplace approximation's draws, said to be no more than that (converged False)
            n = int(self.num_samples) * nc
            z = rng.standard_normal((1, n, D))
            div = np.zeros((1, n), bool)
            mean_tree, step_size = stuck
        else:
            z = np.stack(zs)  # (chains, S, D)
            steps, div = np.stack(steps), np.stack(divs)
            sim.n_simulations += int(steps.sum()) + nc  # leapfrog steps + NumPyro's initial potential
            mean_tree = float(steps[:, int(self.num_warmup) :].mean())
            step_size = float(np.mean(step_sizes))

        x = x_map + z @ chol.T
        fl_arg = base[2] if free_floor else floor  # the floor's prior interval, or the floor
        th, s0s, fls = (
            np.asarray(a) for a in _physical(jnp.asarray(x), fl_arg, jnp.asarray(s0_est), free, free_floor,
                                             box)
        )
        rhat = np.asarray(split_gelman_rubin(th))
        ess = np.asarray(effective_sample_size(th))
        flat = th.reshape(-1, 4)
        n_div = int(div.sum())
        frac_div = n_div / div.size
        problems = []
        if stuck is not None:
            rhat, ess = np.full(4, np.nan), np.full(4, np.nan)
            problems.append(
                f"NUTS stopped after {n_head} warm-up iterations: its trees used {stuck[0]:.3g} "
                f"of the {2 ** int(self.max_tree_depth) - 1} leapfrog steps the depth cap allows "
                f"at a step size of {stuck[1]:.3g} (the posterior is far from Gaussian about its "
                "mode: a ridge or a flat direction); these are the Laplace approximation's draws")
        # a held parameter is constant: nothing to converge (its R-hat is NaN)
        judged = ~self._box(track).held[:3]
        if stuck is None and not np.all(rhat[:3][judged] < 1.05):
            problems.append(f"R-hat {np.round(rhat[:3], 3).tolist()} (e, g, d) not all < 1.05")
        if stuck is None and not np.all(ess[:3][judged] >= 50):
            problems.append(f"ESS {np.round(ess[:3], 1).tolist()} (e, g, d) not all >= 50")
        if frac_div >= 0.02:
            problems.append(f"{n_div} divergent transitions ({100 * frac_div:.1f}%)")
        # how well the mode fits: a wrong basin or a misspecified model shows as RMS >> sigma
        th_map, s0_map, fl_map = (
            np.asarray(a) for a in _physical(jnp.asarray(x_map), fl_arg, jnp.asarray(s0_est), free,
                                             free_floor, box)
        )
        fl_map = float(fl_map) if free_floor else floor
        fit = sim.positions(th_map[None], s0_map[None], T, dt, fl_map)
        rms = float(np.sqrt(mean_sq_error(fit, track.positions, track.mask)[0]))
        if rms > 3.0 * sigma:
            problems.append(f"the mode misses the track by {rms:.3g} m RMS (> 3 sigma = {3 * sigma:.3g} m)")
        extras = {
            "n_simulations": int(sim.n_simulations),
            "wall_s": sw(),
            "rhat": dict(zip(physics.PARAMS, rhat.tolist())),
            "ess": dict(zip(physics.PARAMS, ess.tolist())),
            "divergences": n_div,
            "mean_tree_size": mean_tree,
            "step_size": step_size,
            "converged": not problems,
            "stopped_stuck": stuck is not None,
            "warning": "; ".join(problems),
            "map_rms_m": rms,
            "n_potential_evals_init": pot.n,
            "sigma": sigma,
            "state0_sampled": free,
            "state0_before_contact": track.state0_refit,
            # the floor's posterior; a known floor is its own mean with no spread
            "floor_sampled": free_floor,
            "floor_mean": float(fls.mean()) if free_floor else floor,
            "floor_post_std": float(fls.std(ddof=1)) if free_floor else 0.0,
            **search_info,
            **lap_info,
            **track.describe(),
        }
        if free_floor:
            extras["floor_box"] = [fl_lo, fl_hi]
            extras["floor_rhat"] = float(split_gelman_rubin(fls[..., None])[0])
            extras["floor_ess"] = float(effective_sample_size(fls[..., None])[0])
        # white-noise likelihood: widened where the track errs by more than sigma, in runs of
        # frames, as on every other system (``_fit_on_points``); measured at the mode's
        # trajectory (simulated above). A render's track keeps factor 1, its draws as they are
        k, noise = residual_inflation(track_residuals(fit[0], track), sigma)
        extras.update(noise)
        tb = box_of(track)
        mean = flat.mean(0)
        flat, std = inflate_in_box(flat, mean, flat.std(0, ddof=1), k, tb.lo, tb.span)
        post = Posterior(mean=mean, std=std, samples=flat, extras=extras)
        # per-draw floors when sampled: the model check simulates from their mean, a forecast
        # continues each draw with its own
        floors = fls.reshape(-1) if free_floor else track.floor
        return Fit(post, flat, s0s.reshape(-1, 4), floors, track, sim, sw)

    def _fit_points(self, obs: Observation, part: Points) -> PointsFit:
        """Another system: NUTS on the system's JAX twin (:func:`_fit_on_points`)."""
        return _fit_on_points(self, obs, part)


def _logit(u):
    u = np.clip(np.asarray(u, dtype=np.float64), _EPS, 1.0 - _EPS)
    return np.log(u) - np.log1p(-u)


# ------------------------------------------------------------------------------------------
# the other systems: the points likelihood through the system's JAX twin (was the SystemNUTS
# class of methods/_system_nuts.py)


# ------------------------------------------------------------------------------------------
# the points through JAX
def jax_observer(system):
    """``f(states (T, S), theta (P,)) -> points (T, K, 2)`` in JAX for ``system``.

    """
    return _jax_observer_cached(system.name)


@lru_cache(maxsize=32)
def _jax_observer_cached(name):
    system = _system(name)
    fn = getattr(system, "jax_observe", None)
    if callable(fn):
        return fn
    S, P, K = system.n_state, system.n_params, system.n_points

    def numpy_hook(st, th):
        return system._observe(st[None], th[None])[0]

    try:
        out = jax.eval_shape(numpy_hook, jax.ShapeDtypeStruct((3, S), jnp.float64),
                             jax.ShapeDtypeStruct((P,), jnp.float64))
        if tuple(out.shape) == (3, K, 2):
            return numpy_hook
    except Exception:  # noqa: BLE001 - any failure to trace means: not array-API code
        pass
    # an affine map of the state, the same for every theta (a block's or a puck's centre)
    rng = np.random.default_rng(0)
    n = 4 * (S + 1)
    theta = system.sample_theta(n, rng)
    x = rng.normal(size=(n, S))
    y = system._observe(x[:, None, :], theta)[:, 0].reshape(n, -1)
    A, *_ = np.linalg.lstsq(np.column_stack([x, np.ones(n)]), y, rcond=None)
    y2 = system._observe(x[:, None, :], theta[::-1].copy())[:, 0].reshape(n, -1)
    fit = np.column_stack([x, np.ones(n)]) @ A
    if np.abs(fit - y).max() < 1e-9 and np.abs(y2 - y).max() < 1e-12:
        M, b = A[:S].copy(), A[S].copy()  # NumPy constants: this runs inside a trace, and is cached

        def affine(st, th):
            return (st @ M + b).reshape(st.shape[0], K, 2)

        return affine
    return _pts_callback_observer(system)


#: Relative step of the central differences of a NumPy observation (see _pts_callback_observer).
_OBS_FD = 1e-6


def _pts_callback_observer(system):
    """The NumPy ``_observe`` called from JAX (``pure_callback``), its derivative along a
    tangent by a central difference of two more calls (the points are smooth in the state
    and theta; error ~1e-12 m at these steps): slower than a JAX observation, exact enough."""
    K = system.n_points

    def np_obs(st, th):
        st, th = np.asarray(st, dtype=np.float64), np.asarray(th, dtype=np.float64)
        return np.asarray(system._observe(st[None], th[None])[0], dtype=np.float64)

    @jax.custom_jvp
    def obs(st, th):
        shape = jax.ShapeDtypeStruct((st.shape[0], K, 2), jnp.float64)
        return jax.pure_callback(np_obs, shape, st, th, vmap_method="sequential")

    @obs.defjvp
    def _obs_jvp(primals, tangents):
        st, th = primals
        dst, dth = tangents
        n = jnp.sqrt(jnp.sum(dst * dst) + jnp.sum(dth * dth))
        safe = jnp.where(n > 0, n, 1.0)
        h = _OBS_FD * (1.0 + jnp.sqrt(jnp.sum(st * st) + jnp.sum(th * th)))
        up = obs(st + (h / safe) * dst, th + (h / safe) * dth)
        dn = obs(st - (h / safe) * dst, th - (h / safe) * dth)
        d = jnp.where(n > 0, (up - dn) * (safe / (2.0 * h)), 0.0)
        return obs(st, th), d

    return obs


# ------------------------------------------------------------------------------------------
# the likelihood, with forward-mode derivatives
def _pts_loglik_value(v, data, cfg):
    name, n_frames, dt, P = cfg
    obs, mask, sigma = data
    system = _system(name)
    states = system.jax_simulate()(v[:P], v[P:], n_frames, dt)
    pts = _jax_observer_cached(name)(states, v[:P])
    m = mask[..., None]
    diff = jnp.where(m, pts - jnp.where(m, obs, 0.0), 0.0)
    ll = -0.5 * jnp.sum(diff * diff) / sigma**2
    return jnp.where(jnp.isfinite(ll), ll, -jnp.inf)


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def _pts_loglik(v, data, cfg):
    """Log-likelihood of v = (theta (P,), state0 (S,)); derivatives in forward mode (one
    vectorised ``jvp`` per coordinate: D <= ~8 through a scan of 200 frames is cheaper forward)."""
    return _pts_loglik_value(v, data, cfg)


@_pts_loglik.defjvp
def _pts_loglik_jvp(cfg, primals, tangents):
    v, data = primals
    dv, _ = tangents
    f = lambda w: _pts_loglik_value(w, data, cfg)  # noqa: E731
    val, grad = jax.vmap(lambda t: jax.jvp(f, (v,), (t,)), out_axes=(None, 0))(jnp.eye(v.size))
    return val, jnp.dot(grad, dv)


def _pts_physical(x, data, free, P):
    """Logits x (..., D) -> theta (..., P), state0 (..., S)."""
    s0_fixed, plo, pspan, slo, sspan = data[3:8]
    u = jax.nn.sigmoid(x)
    theta = plo + pspan * u[..., :P]
    if free:
        return theta, slo + sspan * u[..., P:]
    return theta, jnp.broadcast_to(s0_fixed, theta.shape[:-1] + s0_fixed.shape)


def _pts_potential(z, data, *, cfg, free):
    """Minus the log posterior density of the whitened coordinates z (D,)."""
    P = cfg[3]
    x_ref, chol = data[8], data[9]
    x = x_ref + chol @ z
    theta, s0 = _pts_physical(x, data, free, P)
    ll = _pts_loglik(jnp.concatenate((theta, s0)), data[:3], cfg)
    return -(ll + jnp.sum(jax.nn.log_sigmoid(x) + jax.nn.log_sigmoid(-x)))


@lru_cache(maxsize=16)
def _pts_compiled(cfg, free, num_warmup, num_samples, dense_mass, target_accept, max_tree_depth):
    """Jitted potential (value, gradient) and a NUTS chain in jitted blocks for a configuration.

    Returns ``(pe_vg, init, blocks)``: ``init(rng_key, z0, data)`` is NumPyro's initial state
    (the adaptation schedule set for ``num_warmup``) and ``blocks[n](state, data)`` runs ``n``
    iterations in one ``lax.scan``, returning the state and the draws ``(z, num_steps,
    diverging)``. ``n`` is ``num_warmup`` or ``num_samples``: with equal budgets (the report's)
    one compiled block serves warm-up, sampling and every extension of an unconverged chain.
    """
    pe = partial(_pts_potential, cfg=cfg, free=free)
    init_kernel, sample_kernel = hmc(potential_fn_gen=lambda data: partial(pe, data=data),
                                     algo="NUTS")

    @jax.jit
    def init(rng_key, z0, data):
        return init_kernel(z0, num_warmup, dense_mass=dense_mass,
                           target_accept_prob=target_accept, max_tree_depth=max_tree_depth,
                           model_args=(data,), rng_key=rng_key)

    def block(n):
        @jax.jit
        def run(state, data):
            def body(state, _):
                state = sample_kernel(state, model_args=(data,))
                return state, (state.z, state.num_steps, state.diverging)

            return lax.scan(body, state, None, length=n)

        return run

    blocks = {n: block(n) for n in {num_warmup, num_samples}}
    return jax.jit(jax.value_and_grad(lambda z, data: pe(z, data=data))), init, blocks


def _pts_diagnose(th):
    """Split R-hat (P,) and ESS (P,) of draws th (chains, draws, P)."""
    return np.asarray(split_gelman_rubin(th)), np.asarray(effective_sample_size(th))


def _fit_on_points(est, obs: Observation, part: Points) -> PointsFit:
    """:class:`methods.nuts.NUTS` on a system other than the ball (``est`` its instance, ``part``
    the generic points likelihood it composes): NumPyro's NUTS on the system's JAX twin. The
    search refines 5 starts by default (the ball's 3): on the pendulum, where a small change of
    ``b`` and ``mu`` moves the frame at which the bob sticks, 3 refined starts left one of two
    test cases in a wrong local mode 16 posterior std from the truth."""
    sw = Stopwatch()
    prob = part.problem(obs)
    system = prob.system
    if not system.jax_twin:
        raise NotImplementedError(f"nuts is n/a on the {system.name} system: it has no JAX twin")
    if prob.track.scene is not None:
        raise NotImplementedError(f"nuts is n/a on a {system.name} scene other than the "
                                  "default: its JAX twin simulates the default scene only")
    jax_observer(system)  # n/a early, before any work
    P, D, free = prob.P, prob.ndim, prob.free
    T = prob.n_sim_frames
    Tb = _bucket(T, int(est.frame_bucket))
    rng = make_rng(est.seed, 0)

    # 1. the basin: search and least squares on batched NumPy simulations
    starts, info = search(prob, rng, int(est._hp("n_init")), int(est.search_rounds),
                          int(est._hp("n_starts")))
    u_opt, _, opt = refine(prob, starts, int(est.max_opt_evals))

    # 2. the mode and curvature of the potential in logit coordinates
    obs_pad = np.zeros((Tb,) + prob.obs.shape[1:])
    mask = np.zeros((Tb,) + prob.mask.shape[1:], bool)
    obs_pad[:T] = np.where(prob.mask[..., None], prob.obs, 0.0)
    mask[:T] = prob.mask
    base = (jnp.asarray(obs_pad), jnp.asarray(mask), jnp.asarray(prob.sigma, jnp.float64),
            jnp.asarray(prob.track.state0), jnp.asarray(prob.plo), jnp.asarray(prob.pspan),
            jnp.asarray(prob.slo), jnp.asarray(np.maximum(prob.sspan, 1e-12)))
    cfg = (system.name, Tb, float(prob.track.dt), P)
    pe_vg, init, blocks = _pts_compiled(cfg, free, int(est.num_warmup), int(est.num_samples),
                             bool(est.dense_mass), float(est.target_accept),
                             int(est.max_tree_depth))
    pot = _Potential(pe_vg, base, D)
    x0 = _logit(np.clip(u_opt, _EPS, 1 - _EPS))
    x_map, cov, lap = _laplace(pot, [x0])
    chol = np.linalg.cholesky(cov)

    # 3. NUTS in whitened coordinates, chains one after another; while R-hat or ESS miss
    #    their bounds, every chain draws num_samples more (the adapted kernel continues)
    nc, nw, ns = int(est.num_chains), int(est.num_warmup), int(est.num_samples)
    data = base + (jnp.asarray(x_map), jnp.asarray(chol))
    keys = jax.random.split(jax.random.PRNGKey(int(est.seed)), nc)
    states, zs, steps, divs = [], [], [], []
    for c in range(nc):
        z0 = np.zeros(D) if c == 0 else 0.5 * rng.standard_normal(D)
        state = init(keys[c], jnp.asarray(z0), data)
        state, (_, st_w, _) = blocks[nw](state, data)
        state, (zc, st, dv) = blocks[ns](state, data)
        states.append(state)
        zs.append([np.asarray(zc)])
        steps.append([np.asarray(st_w), np.asarray(st)])
        divs.append([np.asarray(dv)])
    n_ext = 0
    while True:
        z = np.stack([np.concatenate(zc) for zc in zs])
        x = x_map + z @ chol.T
        th, s0 = (np.asarray(a) for a in _pts_physical(jnp.asarray(x), data, free, P))
        rhat, ess = _pts_diagnose(th)
        if prob.known:  # a held parameter is constant: nothing to converge (R-hat would be NaN)
            held = [system.params.index(k) for k in prob.known]
            rhat, ess = np.array(rhat, dtype=float), np.array(ess, dtype=float)
            rhat[held], ess[held] = 1.0, float(th.shape[0] * th.shape[1])
        if (np.all(rhat < 1.05) and np.all(ess >= 50)) or n_ext >= int(est.max_extensions):
            break
        n_ext += 1
        for c in range(nc):
            states[c], (zc, st, dv) = blocks[ns](states[c], data)
            zs[c].append(np.asarray(zc))
            steps[c].append(np.asarray(st))
            divs[c].append(np.asarray(dv))
    sizes = [float(st.adapt_state.step_size) for st in states]
    steps = np.stack([np.concatenate(sc) for sc in steps])
    div = np.stack([np.concatenate(dc) for dc in divs])
    flat, s0_flat = th.reshape(-1, P), s0.reshape(-1, prob.S)
    n_div = int(div.sum())
    problems = []
    if not np.all(rhat < 1.05):
        problems.append(f"R-hat {np.round(rhat, 3).tolist()} not all < 1.05")
    if not np.all(ess >= 50):
        problems.append(f"ESS {np.round(ess, 1).tolist()} not all >= 50")
    if n_div / div.size >= 0.02:
        problems.append(f"{n_div} divergent transitions ({100 * n_div / div.size:.1f}%)")
    th_map, s0_map = (np.asarray(a) for a in _pts_physical(jnp.asarray(x_map), data, free, P))
    res = prob.point_residuals(flat.mean(0), s0_flat.mean(0))
    check = prob.check(flat.mean(0), None, res=res)
    map_pts = prob.points(_pts_unit(prob, th_map, s0_map))
    rms = float(np.sqrt(sq_error(map_pts, prob.obs, prob.mask)[0] / max(prob.n_coords, 1)))
    if rms > 3.0 * prob.sigma:
        problems.append(f"the mode misses the track by {rms:.3g} m RMS "
                        f"(> 3 sigma = {3 * prob.sigma:.3g} m)")
    prob.sim.n_simulations += pot.n + int(steps.sum()) + nc
    extras = {
        "n_simulations": int(prob.sim.n_simulations), "wall_s": sw(),
        "rhat": dict(zip(system.params, rhat.tolist())),
        "ess": dict(zip(system.params, ess.tolist())),
        "divergences": n_div, "mean_tree_size": float(steps[:, nw:].mean()),
        "extensions": n_ext, "num_samples_kept": int(z.shape[1]),
        "step_size": float(np.mean(sizes)), "converged": not problems,
        "warning": "; ".join(problems), "map_rms_m": rms, "sigma": prob.sigma,
        "state0_sampled": free, **info, **opt, **lap, **prob.track.describe(),
    }
    # white-noise likelihood: widened where the track errs by more, in runs of frames
    k, noise = noise_inflation(prob, res=res)
    flat_w, std = inflate(prob, flat, flat.std(0, ddof=1), k)
    extras.update(noise)
    post = part.posterior(prob, flat.mean(0), std, flat_w, extras, check)
    return PointsFit(post, flat_w, s0_flat, None, prob, sw)


def _pts_unit(prob, theta, state0):
    """Physical theta (P,) and state0 (S,) -> unit coordinates (1, D) of ``prob``."""
    u = (theta - prob.plo) / np.where(prob.pspan > 0, prob.pspan, 1.0)  # held: span 0, u 0
    if prob.free:
        u = np.concatenate([u, (state0 - prob.slo) / np.maximum(prob.sspan, 1e-12)])
    return u[None]
