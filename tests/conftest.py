import numpy as np
import pytest


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="also run tests marked slow")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    # Benchmarks opt in with --benchmark-only; keep their slow marks from hiding them there.
    if config.getoption("--benchmark-only", default=False):
        return
    skip = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def ball_case():
    """One seeded test-split ball: theta (4,), states (200, 4), 28x28 frames (200, 28, 28)."""
    from sysid_bench.core.physics import sample_state0, sample_theta, simulate
    from sysid_bench.core.render import render

    rng = np.random.default_rng(7)
    theta = sample_theta(1, rng, subranges=(1, 3, 5, 7, 9))
    s0 = sample_state0(1, rng)
    states = simulate(theta, s0)
    frames = render(states)[0]
    return {"theta": theta[0], "state0": s0[0], "states": states[0], "frames": frames}


@pytest.fixture
def one_thread():
    """torch on one thread for the test, restored after (two torch threads on a loaded 2-core
    machine ran small batched passes 10-20x slower)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
