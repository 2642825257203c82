"""CPU per bo fit with the quick GP against skopt's own code, interleaved.

After one untimed warm-up fit per system, each round fits one case with the library path
(``gp_minimize`` with its default estimator and without ``_quick_skopt_helpers``: the code
before them) and with the quick path (which goes first alternates every two rounds), in one
process, checks the two posteriors' hashes are equal and prints the CPU seconds of each::

    PYTHONPATH=$PWD nice -n 10 python scripts/bo_quick_gp_timing.py [n_rounds]
"""

from __future__ import annotations

import contextlib
import statistics
import sys
import time

import methods.bo as bo
from scripts.bo_posterior_hashes import _digest, cases


def _library_gp_minimize(func, n_dims, *, random_state, **options):
    from skopt import gp_minimize

    return gp_minimize(func, [(0.0, 1.0)] * n_dims, random_state=random_state, **options)


def main(n_rounds: int = 5) -> None:
    quick, helpers = bo._gp_minimize, bo._quick_skopt_helpers
    picked = [c for c in cases(("ball", "pendulum")) if c[0] in ("ball0", "ball1", "ball2",
                                                                 "pendulum0", "pendulum1", "pendulum2")]
    for _, est, obs in (picked[0], picked[3]):  # warm-up (compilation, caches), not timed
        est.identify(obs)
    times = {}
    for r in range(n_rounds):
        label, est, obs = picked[r % 3] if r % 2 == 0 else picked[3 + r % 3]
        out = {}
        order = [("library", _library_gp_minimize, contextlib.nullcontext), ("quick", quick, helpers)]
        for name, fn, ctx in order if r % 4 < 2 else order[::-1]:  # which runs first alternates
            bo._gp_minimize, bo._quick_skopt_helpers = fn, ctx
            t0 = time.process_time()
            post = est.identify(obs)
            out[name] = (time.process_time() - t0, _digest(post))
        bo._gp_minimize, bo._quick_skopt_helpers = quick, helpers
        assert out["library"][1] == out["quick"][1], (label, out)
        system = label.rstrip("0123456789")
        times.setdefault(system, []).append((out["library"][0], out["quick"][0]))
        print(f"{label:10s} library {out['library'][0]:5.2f} s  quick {out['quick'][0]:5.2f} s  "
              f"ratio {out['library'][0] / out['quick'][0]:4.2f}  bytes equal", flush=True)
    for system, tt in times.items():
        lib, qk = (statistics.median(x) for x in zip(*tt))
        print(f"{system}: median CPU per fit library {lib:.2f} s, quick {qk:.2f} s, ratio {lib / qk:.2f}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 5)
