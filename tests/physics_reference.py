"""An independent event-driven reference for the bouncing ball, written with scipy's solve_ivp.

It shares nothing with ``sysid_bench.core.physics`` but the constants: adaptive DOP853 at tight
tolerances for flight segments, scipy's own event location for floor and wall contacts, and the
closed form of constant-deceleration rolling. Slow, one trajectory at a time, by design.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from sysid_bench.core.physics import BOX_WIDTH, ROLL_SPEED

RTOL = 1e-12
ATOL = 1e-12


def reference_trajectory(theta, state0, n_frames=200, dt=0.05, floor=0.0, return_roll_time=False):
    """States (n_frames, 4) at the frame times for constant ``theta`` (4,).

    With ``return_roll_time`` also returns the time rolling started (inf if never).
    """
    e, g, d, r = (float(v) for v in theta)
    times = np.arange(n_frames) * dt
    t_end = times[-1]
    out = np.full((n_frames, 4), np.nan)
    out[0] = state0
    s = np.array(state0, dtype=float)
    t = 0.0
    rolling = False
    roll_time = np.inf

    def rhs(_t, u):
        sp = np.hypot(u[2], u[3])
        return [u[2], u[3], -d * sp * u[2], g - d * sp * u[3]]

    def ev_floor(_t, u):
        return u[1] - floor

    ev_floor.terminal, ev_floor.direction = True, -1

    def ev_left(_t, u):
        return u[0]

    ev_left.terminal, ev_left.direction = True, -1

    def ev_right(_t, u):
        return u[0] - BOX_WIDTH

    ev_right.terminal, ev_right.direction = True, 1

    guard = 0
    while t < t_end - 1e-15 and guard < 100000:
        guard += 1
        if not rolling:
            sol = solve_ivp(
                rhs, (t, t_end), s, method="DOP853", rtol=RTOL, atol=ATOL,
                events=(ev_floor, ev_left, ev_right), dense_output=True,
            )
            t_stop = sol.t[-1]
            mask = (times > t) & (times <= t_stop)
            if mask.any():
                out[mask] = sol.sol(times[mask]).T
            if sol.status != 1:  # reached t_end
                break
            s = sol.y[:, -1].copy()
            t = t_stop
            which = [i for i, te in enumerate(sol.t_events) if len(te)]
            for i in which:
                if i == 0:
                    s[1] = floor
                    vy = -e * s[3]
                    if vy < ROLL_SPEED:
                        s[3] = 0.0
                        rolling = True
                        roll_time = t
                    else:
                        s[3] = vy
                elif i == 1:
                    s[0] = 0.0
                    s[2] = -s[2]
                else:
                    s[0] = BOX_WIDTH
                    s[2] = -s[2]
        else:
            # closed form: x(tau) = x + vx tau - r sgn(vx) tau^2 / 2 until the wall or the stop
            x, vx = s[0], s[2]
            if vx == 0.0:
                mask = times > t
                out[mask] = [x, floor, 0.0, 0.0]
                break
            a = -r * np.sign(vx)
            t_halt = abs(vx) / r if r > 0 else np.inf
            wall = BOX_WIDTH if vx > 0 else 0.0
            dist = wall - x  # signed
            disc = vx * vx + 2 * a * dist
            t_wall = np.inf
            if disc >= 0:
                root = (-vx + np.sign(vx) * np.sqrt(disc)) / a if a != 0 else dist / vx
                if root >= 0:
                    t_wall = root
            seg = min(t_halt, t_wall, t_end - t)
            mask = (times > t) & (times <= t + seg)
            tau = times[mask] - t
            out[mask, 0] = x + vx * tau + 0.5 * a * tau**2
            out[mask, 1] = floor
            out[mask, 2] = vx + a * tau
            out[mask, 3] = 0.0
            t += seg
            if seg == t_halt:
                s = np.array([x + vx * seg + 0.5 * a * seg**2, floor, 0.0, 0.0])
                s[2] = 0.0
            elif seg == t_wall:
                s = np.array([wall, floor, -(vx + a * seg), 0.0])
            else:
                break
    if return_roll_time:
        return out, roll_time
    return out
