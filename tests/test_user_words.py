"""Words and numbers a user reads: refusals that show the way on in the user's own terms (flags on the command
line, keywords in Python), results that print short, documents that say what is true."""
from __future__ import annotations

from pathlib import Path

import pytest

import jaxsleigh as js
from jaxsleigh import cli

ROOT = Path(__file__).resolve().parent.parent


def run_cli(argv, capsys):
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return rc, out, err


# ---------------------------------------------------------------------------------------------
# a controller's name where gains are wanted
# ---------------------------------------------------------------------------------------------

def test_gains_shaped_on_the_command_line_says_to_use_controller_shaped(tmp_path, capsys):
    rc, _, err = run_cli(["simulate", "--ic", "1,1,0.5", "--gains", "shaped", "--out", tmp_path / "r.npz"], capsys)
    assert rc == 2 and "use --controller shaped" in err, err
    assert not (tmp_path / "r.npz").exists()


def test_load_gains_of_a_controller_name_says_how_python_takes_it():
    with pytest.raises(ValueError, match=r"controller=make_controller\('shaped'\)"):
        js.load_gains("shaped")


def test_the_readme_presets_say_shaped_is_a_controller_not_gains():
    text = " ".join((ROOT / "README.md").read_text().split())
    assert "`--controller shaped` for the shaped law" in text
    assert "**Gain presets** (`--gains NAME`" not in text
