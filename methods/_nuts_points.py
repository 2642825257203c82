"""NUTS on any registered system other than the ball: the reference posterior, through the
system's JAX twin (what :class:`methods.nuts.NUTS` composes with :mod:`methods._points` there).

The model is :mod:`methods._points`'s: the K tracked points are the twin's states seen
through the system's observation, plus independent Gaussian noise of a fixed ``sigma`` per
coordinate (default ``1.2 * system.noise_m``); a uniform prior on the prior box and, when
``Observation.state0`` is not given, on the initial-state box that ``state0_from_track`` gives
(intersected with the system's ``state_bounds``). NUTS samples the logits of the unit
coordinates (an unconstrained space; the uniform prior there has density
``sigmoid(x) sigmoid(-x)``).

How it runs, as the ball's ``nuts`` (:mod:`methods.nuts`, whose Laplace step it reuses):

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
from jax import lax
from numpyro.diagnostics import effective_sample_size, split_gelman_rubin
from numpyro.infer.hmc import hmc

from methods._points import Points, SystemFit, _system, refine, search, sq_error
from methods._simulation import Stopwatch, make_rng
from methods.nuts import _bucket, _laplace, _logit, _Potential
from sysid_bench.estimator import Observation

__all__ = ["fit_points", "jax_observer"]

_EPS = 1e-6


# ------------------------------------------------------------------------------------------
# the points through JAX
def jax_observer(system):
    """``f(states (T, S), theta (P,)) -> points (T, K, 2)`` in JAX for ``system``.

    """
    return _jax_observer(system.name)


@lru_cache(maxsize=32)
def _jax_observer(name):
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
    return _callback_observer(system)


#: Relative step of the central differences of a NumPy observation (see _callback_observer).
_OBS_FD = 1e-6


def _callback_observer(system):
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
def _loglik_value(v, data, cfg):
    name, n_frames, dt, P = cfg
    obs, mask, sigma = data
    system = _system(name)
    states = system.jax_simulate()(v[:P], v[P:], n_frames, dt)
    pts = _jax_observer(name)(states, v[:P])
    m = mask[..., None]
    diff = jnp.where(m, pts - jnp.where(m, obs, 0.0), 0.0)
    ll = -0.5 * jnp.sum(diff * diff) / sigma**2
    return jnp.where(jnp.isfinite(ll), ll, -jnp.inf)


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def _loglik(v, data, cfg):
    """Log-likelihood of v = (theta (P,), state0 (S,)); derivatives in forward mode (one
    vectorised ``jvp`` per coordinate: D <= ~8 through a scan of 200 frames is cheaper forward)."""
    return _loglik_value(v, data, cfg)


@_loglik.defjvp
def _loglik_jvp(cfg, primals, tangents):
    v, data = primals
    dv, _ = tangents
    f = lambda w: _loglik_value(w, data, cfg)  # noqa: E731
    val, grad = jax.vmap(lambda t: jax.jvp(f, (v,), (t,)), out_axes=(None, 0))(jnp.eye(v.size))
    return val, jnp.dot(grad, dv)


def _physical(x, data, free, P):
    """Logits x (..., D) -> theta (..., P), state0 (..., S)."""
    s0_fixed, plo, pspan, slo, sspan = data[3:8]
    u = jax.nn.sigmoid(x)
    theta = plo + pspan * u[..., :P]
    if free:
        return theta, slo + sspan * u[..., P:]
    return theta, jnp.broadcast_to(s0_fixed, theta.shape[:-1] + s0_fixed.shape)


def _potential(z, data, *, cfg, free):
    """Minus the log posterior density of the whitened coordinates z (D,)."""
    P = cfg[3]
    x_ref, chol = data[8], data[9]
    x = x_ref + chol @ z
    theta, s0 = _physical(x, data, free, P)
    ll = _loglik(jnp.concatenate((theta, s0)), data[:3], cfg)
    return -(ll + jnp.sum(jax.nn.log_sigmoid(x) + jax.nn.log_sigmoid(-x)))


@lru_cache(maxsize=16)
def _compiled(cfg, free, num_warmup, num_samples, dense_mass, target_accept, max_tree_depth):
    """Jitted potential (value, gradient) and a NUTS chain in jitted blocks for a configuration.

    Returns ``(pe_vg, init, blocks)``: ``init(rng_key, z0, data)`` is NumPyro's initial state
    (the adaptation schedule set for ``num_warmup``) and ``blocks[n](state, data)`` runs ``n``
    iterations in one ``lax.scan``, returning the state and the draws ``(z, num_steps,
    diverging)``. ``n`` is ``num_warmup`` or ``num_samples``: with equal budgets (the report's)
    one compiled block serves warm-up, sampling and every extension of an unconverged chain.
    """
    pe = partial(_potential, cfg=cfg, free=free)
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


def _diagnose(th):
    """Split R-hat (P,) and ESS (P,) of draws th (chains, draws, P)."""
    return np.asarray(split_gelman_rubin(th)), np.asarray(effective_sample_size(th))


def fit_points(est, obs: Observation, part: Points) -> SystemFit:
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
    pe_vg, init, blocks = _compiled(cfg, free, int(est.num_warmup), int(est.num_samples),
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
        th, s0 = (np.asarray(a) for a in _physical(jnp.asarray(x), data, free, P))
        rhat, ess = _diagnose(th)
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
    th_map, s0_map = (np.asarray(a) for a in _physical(jnp.asarray(x_map), data, free, P))
    check = prob.check(flat.mean(0), s0_flat.mean(0))
    map_pts = prob.points(_unit(prob, th_map, s0_map))
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
    post = part.posterior(prob, flat.mean(0), flat.std(0, ddof=1), flat, extras, check)
    return SystemFit(post, flat, s0_flat, None, prob, sw)


def _unit(prob, theta, state0):
    """Physical theta (P,) and state0 (S,) -> unit coordinates (1, D) of ``prob``."""
    u = (theta - prob.plo) / prob.pspan
    if prob.free:
        u = np.concatenate([u, (state0 - prob.slo) / np.maximum(prob.sspan, 1e-12)])
    return u[None]
