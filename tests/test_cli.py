import subprocess
import sys

from thermod import cli


def test_usage_lists_every_command(capsys):
    assert cli.main([]) == 2
    out = capsys.readouterr().out
    for name in cli.COMMANDS:
        assert name in out


def test_unknown_command(capsys):
    assert cli.main(["frobnicate"]) == 2
    assert "unknown command 'frobnicate'" in capsys.readouterr().err


def test_every_command_module_has_the_command_interface():
    import importlib
    for name, (module, _) in cli.COMMANDS.items():
        m = importlib.import_module(module)
        assert callable(m.add_arguments) and callable(m.run), name


def test_console_script_help_runs():
    r = subprocess.run([sys.executable, "-m", "thermod.cli", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "deblur" in r.stdout
