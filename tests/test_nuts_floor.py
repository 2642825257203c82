"""NUTS with an unknown floor: the floor is sampled as a nuisance parameter, not held fixed.

Held fixed at ``methods._tracks.prepare``'s estimate (2 cm off on the ball's systems case 0,
positions with 1 cm noise), NUTS put g 8 posterior widths from the truth and passed its model
check. Sampled, the floor's uncertainty reaches the parameters' intervals.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from methods import nuts as N
from sysid_bench.core import physics
from sysid_bench.core import simulator as C


@pytest.mark.slow  # ~20-45 s: compiling the gradient of the 60-frame scan
def test_loglik_gradient_wrt_the_floor_matches_finite_differences():
    """The forward-mode custom derivative with the floor free, for theta, the initial state and
    the floor, vs central differences of the NumPy likelihood, on 60 frames with two bounces."""
    T = 60
    theta0 = np.array([0.8, -9.8, 0.02, 0.1])
    s0 = np.array([2.0, 3.0, 1.5, 0.0])
    obs = physics.simulate(theta0[None], s0[None], n_frames=T)[0, :, :2]
    assert (np.diff(np.sign(np.diff(obs[:, 1]))) > 0).sum() >= 2  # the track bounces
    mask = np.ones(T, bool)
    sigma = C.DEFAULT_SIGMA
    theta = theta0 * np.array([1.01, 0.99, 1.05, 1.0])  # off the mode: gradients are large
    s = s0 + np.array([0.05, -0.03, 0.1, 0.05])
    floor = 0.03

    def np_ll(x):
        sim = physics.simulate(x[None, :4], x[None, 4:8], n_frames=T, floor=x[8])[..., :2]
        return C.gaussian_loglik(sim, obs, mask, sigma)[0]

    def ll(th, st, fl):
        data = (jnp.asarray(obs), jnp.asarray(mask), fl, jnp.asarray(sigma))
        return N._loglik(th, st, data, T, physics.DT, True, True)

    grad = jax.jit(jax.grad(ll, argnums=(0, 1, 2)))
    g = np.concatenate([np.ravel(np.asarray(a)) for a in grad(jnp.asarray(theta), jnp.asarray(s), jnp.asarray(floor))])
    x = np.concatenate((theta, s, [floor]))
    fd = np.empty(9)
    for i in range(9):
        h = 1e-7 * max(abs(x[i]), 1e-2)
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        fd[i] = (np_ll(xp) - np_ll(xm)) / (2 * h)
    assert abs(fd[8]) > 1.0  # the floor matters to this likelihood
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def test_floor_prior_maps_each_draw_to_its_own_state_box():
    """With the floor sampled, a draw's initial height is uniform above its own floor."""
    box = jnp.asarray([-0.2, 0.4])  # floor in [-0.2, 0.2]
    x = jnp.asarray([[0.0] * 8 + [-30.0], [0.0] * 8 + [30.0], [0.0] * 9])
    theta, s0, fl = (np.asarray(a) for a in N._physical(x, box, None, True, True))
    np.testing.assert_allclose(fl, [-0.2, 0.2, 0.0], atol=1e-9)
    np.testing.assert_allclose(s0[:, 1], fl + 0.5 * physics.BOX_WIDTH)
    np.testing.assert_allclose(theta, np.broadcast_to(physics.PRIOR_LO + 0.5 * physics.PRIOR_SPAN, (3, 4)))
    # the known floor keeps today's box and dimension
    assert N._dim(True, False) == 8 and N._dim(False, True) == 5 and N._dim(True, True) == 9


@pytest.mark.slow
def test_noisy_track_without_floor_samples_it_and_the_g_interval_holds():
    """Ball systems case 0 (1 cm position noise; the floor estimate is 2 cm low): held at the
    estimate, g's 90% interval was [-10.52, -10.49] around truth -10.431. Sampled, it must hold
    the truth or at least be wider than with the floor given; the floor's posterior is reported."""
    from sysid_bench.bench.systems import system_case

    obs, truth, _ = system_case("ball", 0, 10, 2024, "positions")
    est = N.NUTS(num_warmup=100, num_samples=100)
    free = est.identify(dataclasses.replace(obs, floor=None))
    given = est.identify(dataclasses.replace(obs, floor=0.0))

    lo, hi = free.interval(0.9)
    lo_k, hi_k = given.interval(0.9)
    holds = lo[1] <= truth[1] <= hi[1]
    print(f"\ng: truth {truth[1]:.4f}, floor sampled [{lo[1]:.4f}, {hi[1]:.4f}], "
          f"floor given [{lo_k[1]:.4f}, {hi_k[1]:.4f}]")
    assert holds or (hi[1] - lo[1]) > (hi_k[1] - lo_k[1])
    ex = free.extras
    assert ex["floor_sampled"] is True and given.extras["floor_sampled"] is False
    assert np.isfinite(ex["floor_mean"]) and ex["floor_post_std"] > 0
    lo_f, hi_f = ex["floor_box"]
    assert lo_f < ex["floor_mean"] < hi_f
    # the data pull the floor from the estimate (ex["floor"]) towards the truth, 0
    assert abs(ex["floor_mean"]) < abs(ex["floor"])
    assert given.extras["floor_mean"] == 0.0 and given.extras["floor_post_std"] == 0.0
    assert free.samples.shape == (100, 4) and free.check.ok
