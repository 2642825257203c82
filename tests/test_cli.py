"""``sysid-bench``: one command, shared option groups, subcommands added by one line."""

import subprocess
import sys
import types

import pytest

from sysid_bench.apps import cli


def test_list_and_module_entry_points():
    assert cli.main(["list"]) == 0
    out = subprocess.run([sys.executable, "-m", "sysid_bench", "--help"], capture_output=True,
                         text=True, check=True).stdout
    for name in ("list", "run", "report", "train", "evaluate"):
        assert name in out


def test_report_module_is_an_alias_of_the_report_subcommand(capsys):
    with pytest.raises(SystemExit) as a:
        cli.main(["report", "--help"])
    text = capsys.readouterr().out
    from sysid_bench.apps.report import main as report_main

    with pytest.raises(SystemExit) as b:
        report_main(["--help"])
    assert a.value.code == b.value.code == 0
    assert capsys.readouterr().out == text
    assert "--threads" in text and "--scheduler" in text and "--from-store" in text


@pytest.mark.parametrize("command, prog", [("train", "methods.vid2param.train"),
                                           ("evaluate", "methods.vid2param.evaluate")])
def test_train_and_evaluate_delegate_with_their_arguments(command, prog, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main([command, "--help"])
    assert e.value.code == 0 and prog in capsys.readouterr().out


def test_a_subcommand_is_one_module_and_one_line(monkeypatch, capsys):
    mod = types.ModuleType("fake_subcommand")

    def add_arguments(p):
        cli.options.seed(p)
        cli.options.out(p, "somewhere")

    def run(args):
        print(f"seed={args.seed} out={args.out}")
        return 0

    mod.add_arguments, mod.run = add_arguments, run
    monkeypatch.setitem(sys.modules, "fake_subcommand", mod)
    monkeypatch.setitem(cli.SUBCOMMANDS, "fake", ("fake_subcommand", "a test subcommand"))
    assert cli.main(["fake", "--seed", "3"]) == 0
    assert capsys.readouterr().out.strip() == "seed=3 out=somewhere"


def test_errors_are_one_line_and_status_2(capsys):
    assert cli.main(["run", "--scale", "smoke", "--methods", "prio", "--no-progress"]) == 2
    assert "Did you mean 'prior'" in capsys.readouterr().err


def test_the_chosen_subcommand_alone_is_imported():
    code = ("import sys; from sysid_bench.apps.cli import main\n"
            "try:\n    main(['run', '--help'])\nexcept SystemExit:\n    pass\n"
            "print('torch' in sys.modules, 'jax' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split()[-2:] == ["False", "False"]


def test_cli_runs_as_a_module():
    """``python -m sysid_bench.cli run --help`` (the module as __main__) finds its own
    subcommands (it looked them up by module name and raised AttributeError)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", "sysid_bench.apps.cli", "run", "--help"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "usage: sysid-bench run" in out.stdout
