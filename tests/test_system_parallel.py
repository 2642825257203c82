"""The pendulum's and spring's parallel kernels (large batches) equal their serial ones bitwise."""

import threading

import numpy as np
import pytest

from sysid_bench.core import systems
from sysid_bench.core.systems import _base, pendulum, spring


def test_use_parallel_rule():
    assert _base.use_parallel(_base.PARALLEL_MIN)
    assert not _base.use_parallel(_base.PARALLEL_MIN - 1)
    seen = []
    t = threading.Thread(target=lambda: seen.append(_base.use_parallel(10**6)))
    t.start()
    t.join()
    assert seen == [False]  # never from a worker thread


@pytest.mark.parametrize("name", ["pendulum", "spring"])
def test_parallel_kernel_bitwise_serial(name, monkeypatch):
    system = systems.get(name)
    theta, state0 = system.sample_cases(_base.PARALLEL_MIN, np.random.default_rng(5))
    par = system.simulate(theta, state0, 60)
    module = pendulum if name == "pendulum" else spring
    monkeypatch.setattr(module, "use_parallel", lambda batch: False)
    ser = system.simulate(theta, state0, 60)
    assert np.array_equal(par, ser)
    # parameters that change over time go through the same kernels
    varying = np.repeat(theta[:, None], 60, axis=1)
    assert np.array_equal(system.simulate(varying, state0, 60), ser)
