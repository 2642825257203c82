"""The lazy registry: names, lazy imports, helpful errors."""

import subprocess
import sys

import pytest

import methods
from sysid_bench.estimator import Estimator


def test_available_lists_the_design_names():
    assert methods.available() == ["vid2param", "nuts", "emcee", "lsq", "bo", "sindy", "dmd"]
    assert "prior" in methods.available(include_reference=True)


def test_importing_methods_loads_neither_torch_nor_jax():
    code = "import sys, methods; methods.get('prior'); print('torch' in sys.modules, 'jax' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_unknown_name_lists_known_and_suggests():
    with pytest.raises(ValueError) as info:
        methods.get("nut")
    msg = str(info.value)
    assert "lsq" in msg and "vid2param" in msg and "Did you mean 'nuts'" in msg


def test_get_passes_options_and_rejects_unknown_ones():
    est = methods.get("prior", n_samples=10, seed=3)
    assert isinstance(est, Estimator) and est.get_params() == {"n_samples": 10, "seed": 3}
    with pytest.raises(ValueError, match="options"):
        methods.get("prior", bogus=1)


def test_register_validates():
    with pytest.raises(ValueError, match="entry_point"):
        methods.register("x", "no_colon")
    with pytest.raises(ValueError, match="already registered"):
        methods.register("lsq", "methods.lsq:LSQ")
