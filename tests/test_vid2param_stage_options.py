"""The options of Vid2Param's stages (``--stages NAME:KEY=VALUE``): a misspelt or unknown option
is a ValueError naming the stage and the option, before anything is trained or fitted; each
stage names the options its fit takes."""

from __future__ import annotations

from dataclasses import fields

import pytest

from methods.vid2param.stages import PRESET_STAGES, STAGES
from methods.vid2param.train import parse_stages


def test_each_stage_names_the_options_its_fit_takes():
    from methods.vid2param.drag import DragFitConfig
    from methods.vid2param.fit_prior import PriorFitConfig

    assert STAGES["std_scale"].fit_options() == ("n", "seed")
    assert set(STAGES["prior_noise"].fit_options()) == {f.name for f in fields(PriorFitConfig)}
    assert set(STAGES["drag_evidence"].fit_options()) == {f.name for f in fields(DragFitConfig)}
    assert STAGES["physics_calibration"].fit_options() == ("n", "seed")
    # every preset's options are ones its stages take
    for preset, stages in PRESET_STAGES.items():
        assert parse_stages(stages) == [(n, dict(o)) for n, o in stages], preset


@pytest.mark.parametrize("spec, stage, option", [
    ("std_scale:nn=3", "std_scale", "nn"),  # was dropped silently: defaults fitted
    ("prior_noise:stepz=3", "prior_noise", "stepz"),  # was a TypeError deep in the fit
    ("drag_evidence:n_videos=3,kk=2", "drag_evidence", "kk"),
    ("physics_calibration:n=5,threads=2", "physics_calibration", "threads"),
])
def test_an_unknown_option_is_refused_naming_stage_and_option(spec, stage, option):
    with pytest.raises(ValueError, match=rf"stage '{stage}' has no option '{option}' "
                                         r"\(its options: "):
        parse_stages([spec])
    with pytest.raises(ValueError, match=rf"'{option}'"):
        parse_stages([(stage, {option: 1})])  # the (name, options) form too


def test_known_options_pass_and_keep_takes_no_others():
    assert parse_stages(["std_scale:n=5,seed=2", "prior_noise:keep=true"]) == [
        ("std_scale", {"n": 5, "seed": 2}), ("prior_noise", {"keep": True})]
    with pytest.raises(ValueError, match=r"'prior_noise' is kept as fitted .*\['steps'\]"):
        parse_stages(["prior_noise:keep=true,steps=3"])


def test_the_training_command_refuses_a_bad_stage_before_training(tmp_path):
    from methods.vid2param.train import main

    out = tmp_path / "run"
    with pytest.raises(ValueError, match=r"stage 'std_scale' has no option 'nn'"):
        main(["--out", str(out), "--steps", "1", "--export", str(tmp_path / "f.pt"),
              "--stages", "std_scale:nn=3", "--no-progress"])
    assert not out.exists()  # nothing trained
