"""Words and numbers a user reads: refusals that show the way on in the user's own terms (flags on the command
line, keywords in Python), results that print short, documents that say what is true."""
from __future__ import annotations

from pathlib import Path

import numpy as np
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


# ---------------------------------------------------------------------------------------------
# a run too small for the default audit: the advice in the caller's terms
# ---------------------------------------------------------------------------------------------

def _small_run_record():
    from jaxsleigh.studies.audit import Audit, audit_rows

    class Rows:                             # three rows: fewer than the audit's 500, so nothing is re-run
        status = np.zeros(3, np.int32)

    return audit_rows(Rows(), lambda *a: pytest.fail("re-ran rows of a small run"), Audit())


def test_the_command_line_names_the_audit_flag_for_a_small_run(capsys):
    from jaxsleigh.cli.chunked import say_study_done

    class Result:
        status, T_eps = np.zeros(3, np.int32), np.full(3, np.inf)
        settings = {"dtype": "float32", "method": "adaptive"}
        run_info = {"audit": _small_run_record()}

    say_study_done("basin", Result(), {"wall_s": 1.0}, ["b.npz"], 0.05)
    out = capsys.readouterr().out
    assert "accuracy audit: not run (fewer than 500 starts; --audit-rows K audits a small run)" in out, out
    assert "RunOptions" not in out


def test_python_keeps_the_python_advice_for_a_small_run():
    from jaxsleigh.studies.audit import audit_line

    rec = _small_run_record()
    assert rec["rows"] == 0 and rec["why"] == "fewer than 500 starts"
    assert "run=jaxsleigh.RunOptions(audit=jaxsleigh.Audit(rows=k))" in audit_line(rec)
    # a record written by an earlier version (its advice inside "why") is worded for the command line too
    old = {"rows": 0, "why": "fewer than 500 starts (pass run=jaxsleigh.RunOptions(audit=jaxsleigh.Audit(rows=k)) "
                             "to audit a small run)"}
    assert audit_line(old, flag="--audit-rows") == ("accuracy audit: not run (fewer than 500 starts; --audit-rows K "
                                                    "audits a small run)")
