"""How hard is it for an LSTM to read the parameters off a ball's track? (a design probe)

Trains a plain LSTM (hidden 128, Gaussian NLL on the normalised parameters) on simulated
tracks for 600 steps of 16 and prints the test nMSE of e, g, d, r every 100 steps.

    python scripts/lstm_probe.py pos 0        # positions only, no noise
    python scripts/lstm_probe.py posvel 0     # positions and true velocities
    python scripts/lstm_probe.py diff 0.005   # positions + scaled 1st/2nd differences, 5 cm noise

Measured on the 2-core CPU (2026-11-22, under load): with positions (or positions and
velocities) g stayed at prior level (~0.08) after 600 steps; with the difference features it
fell to ~0.005 by step 500, also with 5 cm position noise. This is why Vid2Param has
``V2PConfig.diff_features``.
"""

import sys
import time

import numpy as np
import torch

from sysid_bench.physics import normalise_theta, sample_state0, sample_theta, simulate


def main(mode: str, noise: float, steps: int = 600, seed: int = 0) -> None:
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    n = 4000
    theta = sample_theta(n, rng, subranges=(0, 2, 4, 6, 8))
    states = simulate(theta, sample_state0(n, rng), n_frames=100)
    pos = states[..., :2] / 10.0 + noise * rng.standard_normal(states[..., :2].shape)
    if mode == "pos":
        inp = pos
    elif mode == "posvel":
        inp = np.concatenate([pos, states[..., 2:] / 16.0], -1)
    elif mode == "diff":
        vel = np.diff(pos, axis=1, prepend=pos[:, :1]) * 10
        acc = np.diff(vel, axis=1, prepend=vel[:, :1]) * 40
        inp = np.concatenate([pos, vel, acc], -1)
    else:
        raise ValueError(f"mode: expected pos, posvel or diff, got {mode!r}")
    x = torch.tensor(inp, dtype=torch.float32)
    y = torch.tensor(normalise_theta(theta), dtype=torch.float32)
    lstm = torch.nn.LSTM(x.shape[-1], 128, batch_first=True)
    head = torch.nn.Linear(128, 8)
    opt = torch.optim.Adam([*lstm.parameters(), *head.parameters()], 1e-3)
    t0 = time.time()
    for step in range(steps):
        idx = torch.randint(0, n - 500, (16,))
        out = head(lstm(x[idx])[0])
        mu, sd = out[..., :4], torch.nn.functional.softplus(out[..., 4:]) + 1e-3
        loss = (torch.log(sd) + 0.5 * ((y[idx][:, None] - mu) / sd) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 100 == 99:
            with torch.no_grad():
                mu = head(lstm(x[-500:])[0])[:, -1, :4]
                mse = ((mu - y[-500:]) ** 2).mean(0).numpy()
            print(mode, step + 1, f"{time.time() - t0:.0f}s", np.round(mse, 4), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]) if len(sys.argv) > 2 else 0.0)
