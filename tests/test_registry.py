"""The lazy registry: names, lazy imports, helpful errors."""

import subprocess
import sys

import pytest

import methods
from sysid_bench.core.estimator import Estimator


def test_available_lists_contenders_and_reference_helpers_apart():
    every = methods.available(include_reference=True)
    assert every == list(methods._REGISTRY)  # registration order
    assert methods.available() == [n for n in every if n not in methods.references()]
    assert methods.references() and set(methods.references()) <= set(every)


@pytest.mark.parametrize("name", methods.available(include_reference=True))
def test_every_registration_declares_a_valid_spec_under_its_name(name):
    try:
        spec = methods.spec(name)
    except ImportError as exc:
        pytest.skip(str(exc))
    assert spec.name == name and spec.entry_point == methods._REGISTRY[name].entry_point
    assert spec.input_kind in ("positions", "frames")
    assert spec.identifies or spec.forecasts


def test_exactly_one_reference_posterior():
    refs = []
    for n in methods.available(include_reference=True):
        try:
            if methods.spec(n).reference_posterior:
                refs.append(n)
        except ImportError:
            pass
    assert len(refs) <= 1


def test_bad_declarations_name_the_attribute():
    from sysid_bench.core.estimator import Estimator

    class Odd(Estimator):
        name = "odd"
        input_kind = "pixels"

        def __init__(self, *, seed: int = 0):
            self.seed = seed

        def identify(self, obs):
            raise NotImplementedError("odd identifies nothing at all")

    with pytest.raises(ValueError, match="Odd.input_kind"):
        Odd.spec()

    class Odd2(Odd):
        input_kind = "positions"
        scale_options = {"smoke": {"bogus": 1}}

    with pytest.raises(ValueError, match="Odd2.scale_options"):
        Odd2.spec()


def test_unregister():
    methods.register("tmp-prior", "methods.prior:PriorOnly")
    with pytest.raises(ValueError, match="declares name 'prior'"):
        methods.get("tmp-prior")
    methods.unregister("tmp-prior")
    assert "tmp-prior" not in methods.available(include_reference=True)


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
    assert isinstance(est, Estimator)
    assert est.get_params() == {"system": "ball", "n_samples": 10, "seed": 3, "known": None,
                                "prior": None}
    with pytest.raises(ValueError, match="options"):
        methods.get("prior", bogus=1)


def test_register_validates():
    with pytest.raises(ValueError, match="entry_point"):
        methods.register("x", "no_colon")
    with pytest.raises(ValueError, match="already registered"):
        methods.register("lsq", "methods.lsq:LSQ")


def test_reading_a_declaration_imports_only_that_method():
    # declarations live on the class, so reading one imports its module, and only that one
    code = ("import sys, methods; s = methods.spec('lsq'); "
            "print(s.cost, 'torch' in sys.modules, 'jax' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["8", "False", "False"]


def test_the_registry_docstring_lists_what_is_registered():
    # the module's doctest shows methods.available(): it must stay what the registry holds
    import doctest

    import methods

    res = doctest.testmod(methods, verbose=False, report=False)
    assert res.attempted >= 2 and res.failed == 0, res
