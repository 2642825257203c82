"""The ``kalman`` policy: a constant-acceleration Kalman filter per axis with bounce and wall
detection, predicting the crossing ballistically."""

from __future__ import annotations

import math

import numpy as np

from sysid_bench.bench.intercept.policies import _ForecastTarget
from sysid_bench.core import physics
from sysid_bench.core._validate import check_positive_int


class Kalman(_ForecastTarget):
    """Constant-acceleration Kalman filter per axis on tracked positions; ballistic prediction.

    Bounces are detected when a measurement lands well above the prediction of a falling ball
    (then the contact time is solved for with the current restitution estimate, the floor is
    read at it and the vertical velocity reflected); walls at x = 0 and 10 reflect the
    horizontal state. Restitution is re-estimated a few frames after each bounce. The forecast
    is the suite's simulator run from the filtered state with the filter's gravity, restitution
    and floor and no drag or rolling resistance.

    Parameters
    ----------
    sigma : float
        Tracking noise std, m.
    q : float
        White-jerk spectral density of the filter (m^2/s^5).
    e0 : float
        Restitution before any bounce was measured.
    floor0 : float or None
        Floor guess before the first bounce; None: half the scene's floor offset range.
    every : int
        Replan every this many frames.
    """

    name = "kalman"

    def __init__(self, sigma: float = 0.08, q: float = 2.0, e0: float = 0.8, floor0=None,
                 every: int = 1):
        self.sigma, self.q, self.e0, self.floor0 = float(sigma), float(q), float(e0), floor0
        self.every = check_positive_int(every, "every")

    def reset(self, scene, rng, throw=None):
        super().reset(scene, rng, throw)
        dt = scene.dt
        self.F = np.array([[1.0, dt, dt * dt / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
        q = self.q
        self.Q = q * np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6],
                               [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                               [dt**3 / 6, dt**2 / 2, dt]])
        self.s = None  # (2, 3): x and y states [p, v, a]
        self.P = None  # (2, 3, 3)
        self.floor = (0.5 * float(scene.nuisance.get("floor_offset", 0.0))
                      if self.floor0 is None else float(self.floor0))
        self.floor_seen = False
        self.n_floor = 0
        self.e_est = []
        self.bounce = None  # (t_contact, v_before, frames since) awaiting an e estimate
        self.t_last = None

    def _init(self, z, t):
        g0 = -9.81
        self.s = np.array([[z[0], 0.0, 0.0], [z[1], 0.0, g0]])
        self.P = np.array([np.diag([self.sigma**2, 64.0, 0.5]), np.diag([self.sigma**2, 25.0, 4.0])])
        self.t_last = t

    @property
    def e(self):
        return float(np.clip(np.mean(self.e_est), 0.3, 1.0)) if self.e_est else self.e0

    def _update(self, i, z):
        H = np.array([1.0, 0.0, 0.0])
        S = self.P[i][0, 0] + self.sigma**2
        K = self.P[i][:, 0] / S
        self.s[i] = self.s[i] + K * (z - self.s[i][0])
        self.P[i] = self.P[i] - np.outer(K, H @ self.P[i])

    def act(self, frame, k):
        from sysid_bench.core.tracking import track

        sc = self.scene
        t = k * sc.dt
        self._t_prev = t - sc.dt
        z = track(frame[None])[0]
        seen = bool(np.all(np.isfinite(z)))
        if self.s is None:
            if not seen:
                return self.target
            self._init(z, t)
        else:
            prev = self.s.copy()
            for i in range(2):
                self.s[i] = self.F @ self.s[i]
                self.P[i] = self.F @ self.P[i] @ self.F.T + self.Q
            # walls: elastic and at known places (the camera is framed on the box)
            for wall, out in ((0.0, self.s[0, 0] < 0.0),
                              (physics.BOX_WIDTH, self.s[0, 0] > physics.BOX_WIDTH)):
                if out:
                    self.s[0, 0] = 2 * wall - self.s[0, 0]
                    self.s[0, 1] = -self.s[0, 1]
            bounced = False
            if seen:
                gate = max(0.3, 4.0 * math.sqrt(self.P[1][0, 0] + self.sigma**2))
                falling = prev[1, 1] < 0
                below = self.s[1, 0] < (self.floor if self.floor_seen else prev[1, 0])
                if falling and (z[1] - self.s[1, 0] > gate or (self.floor_seen and below)):
                    bounced = self._bounce(prev, z[1])
                if abs(z[0] - self.s[0, 0]) < 3.0:  # occlusion can shift a centroid: gate it
                    self._update(0, z[0])
                if bounced or abs(z[1] - self.s[1, 0]) < 3.0:
                    self._update(1, z[1])
            elif self.floor_seen and self.s[1, 0] < self.floor and prev[1, 1] < 0:
                self._bounce(prev, None)
            if self.bounce is not None and not bounced:
                tc, vb, n = self.bounce
                n += 1 if seen else 0
                if n >= 4:
                    va = self.s[1, 1] - self.s[1, 2] * (t - tc)
                    if vb < -0.5 and va > 0:
                        self.e_est.append(float(np.clip(va / -vb, 0.3, 1.0)))
                    self.bounce = None
                else:
                    self.bounce = (tc, vb, n)
            self.s[1, 2] = float(np.clip(self.s[1, 2], -13.5, -6.0))
        if k % self.every:
            return self.target
        return self._predict(t)

    def _bounce(self, prev, zy):
        """A floor contact between the previous frame and now: solve its time, reflect vy."""
        dt = self.scene.dt
        y0, v0, a = prev[1]
        e = self.e
        tau = np.linspace(0.0, dt, 41)
        fl = y0 + v0 * tau + a * tau**2 / 2
        vc = v0 + a * tau
        rest = dt - tau
        y1 = fl - e * vc * rest + a * rest**2 / 2
        if zy is None:
            j = int(np.argmin(np.abs(fl - self.floor)))
        else:
            j = int(np.argmin(np.abs(y1 - zy)))
        if vc[j] >= 0:
            return False
        if zy is not None:
            # floor estimates: running mean over bounces (the first replaces the guess)
            n = self.n_floor
            self.floor = (self.floor * n + fl[j]) / (n + 1)
            self.n_floor = n + 1
            self.floor_seen = True
        self.s[1, 0] = y1[j]
        self.s[1, 1] = -e * vc[j] + a * rest[j]
        self.P[1][1, 1] += 4.0  # the restitution is uncertain: so is the new velocity
        self.bounce = (self._t_prev + tau[j], float(vc[j]), 0)
        return True

    def _predict(self, t):
        sc = self.scene
        h = self._horizon(int(round(t / sc.dt)))
        x, vx = self.s[0, 0], self.s[0, 1]
        y, vy, ay = self.s[1, 0], self.s[1, 1], self.s[1, 2]
        floor = self.floor
        x = float(np.clip(x, 0.0, physics.BOX_WIDTH))
        y = float(np.clip(y, floor, floor + physics.BOX_WIDTH))
        theta = np.array([[self.e, ay, 0.0, 0.0]])
        st = physics.simulate(theta, np.array([[x, y, vx, vy]]), n_frames=h + 1, dt=sc.dt,
                              floor=floor)[0, 1:, :2]
        # the band: the filter's covariance carried forward by the constant-acceleration model
        # (bounces and walls ignored), J_k = [1, k dt, (k dt)^2 / 2]
        tk = sc.dt * np.arange(1, h + 1)
        J = np.stack([np.ones_like(tk), tk, tk**2 / 2], axis=1)
        std = np.sqrt(np.stack([np.einsum("hi,ij,hj->h", J, self.P[i], J) for i in range(2)], 1))
        return self._aim(t, (x, y), st, std)


