"""The latent rollout's transition: known physics on the latent state, plus learned noise.

The paper "integrates a physically based dynamics model with a recurrent variational
autoencoder". Here the prior's mean of the ball's state ``[x, y, vx, vy]`` at the next frame is
one frame of ``sysid_bench.core.physics`` applied to the latent state with the latent parameters
(``e, g, d, r``, which persist along the rollout), and its std a learned per-frame process
noise. The physics stays the suite's one NumPy source: it is called, not re-coded.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from methods.vid2param.rollout import clamp_state
from sysid_bench.core.physics import PARAMS, PRIOR, simulate

__all__ = ["PhysicsPrior", "NOISE0", "BOUNCE_NOISE0", "SKILL_REF", "SKILL_RANGE", "physics_step"]

_LO = np.array([PRIOR[p][0] for p in PARAMS])
_HI = np.array([PRIOR[p][1] for p in PARAMS])
#: Starting per-frame process noise of x, y (m) and vx, vy (m/s); ``PhysicsPrior.log_noise``
#: is trained from there (see ``methods.vid2param.fit_prior``).
NOISE0 = (0.001, 0.001, 0.005, 0.005)
#: Starting noise of vx and vy at a floor bounce, relative to their size: a real ball's bounce
#: loses horizontal speed to spin and time to a soft contact, which our physics does not model.
BOUNCE_NOISE0 = (0.05, 0.05)
#: Backtest error (m, ``rollout.backtest_error``) at which the noise is the learned one: the
#: noise is scaled by ``(skill / SKILL_REF) ** gain``, so a gain of 0 (the starting value, and
#: that of priors trained before the gain existed) ignores the backtest.
SKILL_REF = 0.05
#: Backtest errors are clipped to this range (m) first: below it the keypoints' own noise, above
#: it a failed fit.
SKILL_RANGE = (0.002, 2.0)


def physics_step(state: np.ndarray, theta: np.ndarray, dt: float) -> np.ndarray:
    """One frame of ``sysid_bench.core.physics.simulate`` for each row.

    Parameters
    ----------
    state : ndarray, shape (S, 4)
        ``[x, y, vx, vy]``, floor-relative metres and m/s (``rollout.clamp_state`` first).
    theta : ndarray, shape (S, 4)
        ``(e, g, d, r)``, clipped to the prior.

    Returns
    -------
    ndarray, shape (S, 4)
    """
    return simulate(np.clip(theta, _LO, _HI), clamp_state(state), 2, dt)[:, 1]


class PhysicsPrior(nn.Module):
    """p(s_{t+1} | s_t, theta): one frame of physics, with a learned process noise.

    The noise is what the rollout does not know: a small per-frame std of x, y (m) and vx, vy
    (m/s), and at a floor bounce a std of vx and vy proportional to their size (model mismatch
    of real bounces: spin, soft contacts). Both are scaled per particle by how well our physics
    forecast the frames already seen (``skill``: ``(skill / SKILL_REF) ** skill_gain``, one gain
    for the per-frame noise and one for the bounce's): on clean video a single noise fitted to
    a mix of clean and deviating balls held 96% in its 90% bands. Trained by
    ``methods.vid2param.fit_prior``; a noise spread over every frame instead (measured: x 0.037 m, vx 0.16 m/s per frame after training
    on half-perturbed videos) widened clean forecasts to 2 m bands and doubled their MSE.
    """

    def __init__(self):
        super().__init__()
        self.log_noise = nn.Parameter(torch.log(torch.tensor(NOISE0, dtype=torch.float32)))
        self.log_bounce = nn.Parameter(torch.log(torch.tensor(BOUNCE_NOISE0, dtype=torch.float32)))
        self.skill_gain = nn.Parameter(torch.zeros(2))  # per-frame noise, bounce noise

    def forward(self, state: torch.Tensor, theta: torch.Tensor, dt: float,
                skill: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and std of the next state.

        Parameters
        ----------
        state : Tensor, shape (S, 4)
            Floor-relative metres and m/s.
        theta : Tensor, shape (S, 4)
            Physical units.
        skill : Tensor, shape (S,), optional
            Backtest error per particle (m, ``rollout.backtest_error``); None or NaN: ``SKILL_REF``.

        Returns
        -------
        mean, std : Tensor, shape (S, 4)
        """
        nxt = torch.as_tensor(
            physics_step(state.detach().cpu().numpy(), theta.detach().cpu().numpy(), dt),
            dtype=state.dtype, device=state.device,
        )
        # straight through the step with the gradient of free flight (x += v dt): the physics
        # is not differentiated, but the noise added to a velocity moves later positions
        lin = torch.cat([state[:, :2] + dt * state[:, 2:], state[:, 2:]], -1)
        mean = lin + (nxt - lin).detach()
        std = torch.exp(self.log_noise).expand_as(mean)
        bounce = ((state[:, 3] < 0) & (nxt[:, 3] > 0)).to(mean.dtype)[:, None]  # (S, 1)
        rel = torch.exp(self.log_bounce) * nxt[:, 2:].abs().detach()  # (S, 2)
        if skill is not None:
            scale = torch.exp(self.skill_gain[None, :] * self.log_skill(skill)[:, None])  # (S, 2)
            std, rel = std * scale[:, :1], rel * scale[:, 1:]
        std = torch.cat([std[:, :2], torch.sqrt(std[:, 2:] ** 2 + bounce * rel**2)], -1)
        return mean, std

    @staticmethod
    def log_skill(skill: torch.Tensor) -> torch.Tensor:
        """``log(skill / SKILL_REF)`` (S,), clipped to ``SKILL_RANGE``; 0 where NaN."""
        s = torch.nan_to_num(skill, nan=SKILL_REF).clamp(*SKILL_RANGE)
        return torch.log(s / SKILL_REF)
