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
    assert "the shaped law: `--controller shaped`" in text and "(`--controller shaped`) |" in text
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


# ---------------------------------------------------------------------------------------------
# the same run twice at once: told it is the same run, not one with other settings
# ---------------------------------------------------------------------------------------------

HOLDER = """
import sys, time
from jaxsleigh.files.runlock import RunLock
RunLock(sys.argv[1], sys.argv[2]).acquire()
print("ready", flush=True)
time.sleep(120)
"""


@pytest.fixture
def holder():
    """``holder(target, fingerprint)``: a real process holding the lock on ``target`` with that fingerprint."""
    import os
    import subprocess
    import sys

    procs = []

    def start(target, fingerprint):
        env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        p = subprocess.Popen([sys.executable, "-c", HOLDER, str(target), fingerprint], stdout=subprocess.PIPE,
                             env=env, text=True)
        procs.append(p)
        assert p.stdout.readline().strip() == "ready"
        return p

    yield start
    for p in procs:
        p.kill()
        p.wait(timeout=30)
        p.stdout.close()


def test_the_same_simulate_twice_on_one_out_is_told_the_same_run_is_in_progress(tmp_path, capsys, holder):
    from jaxsleigh.cli import build_parser
    from jaxsleigh.cli.common import EXIT_LOCKED, run_fingerprint

    argv = ["simulate", "--ic", "1,1,0.5", "--t-final", "0.1", "--out", str(tmp_path / "r.npz")]
    p = holder(tmp_path / "r.npz", run_fingerprint(build_parser().parse_args(argv)))
    rc, _, err = run_cli(argv, capsys)
    assert rc == EXIT_LOCKED and "the same run is in progress" in err and f"pid {p.pid}" in err, err
    assert "other settings" not in err
    rc, _, err = run_cli(argv[:-2] + ["--t-final", "0.2", "--out", tmp_path / "r.npz"], capsys)
    assert rc == EXIT_LOCKED and "other settings" in err, err          # other settings: said so


def test_the_fingerprint_is_the_settings_not_the_look():
    from jaxsleigh.cli import build_parser
    from jaxsleigh.cli.common import run_fingerprint

    parse = build_parser().parse_args
    base = ["simulate", "--ic", "1,1,0.5", "--out", "r.npz"]
    assert run_fingerprint(parse(base)) == run_fingerprint(parse(base))
    assert run_fingerprint(parse(base)) == run_fingerprint(parse(base + ["--no-progress"]))
    assert run_fingerprint(parse(base)) != run_fingerprint(parse(base + ["--t-final", "5"]))


def test_run_to_file_twice_with_the_same_options_is_told_the_same_run_is_in_progress(tmp_path, holder):
    from jaxsleigh.errors import RunLockedError
    from jaxsleigh.files.runner import _single_run_id, run_to_file

    out, options = tmp_path / "mc.npz", {"samples": 4, "seed": 1}
    holder(out, _single_run_id([str(out), options]))

    def study(**kw):
        raise AssertionError("computed while the same run held the output")

    with pytest.raises(RunLockedError, match="the same run is in progress"):
        run_to_file(out, study, js.save_basin, options=options)


# ---------------------------------------------------------------------------------------------
# kept chunks of a finished run are a finished run's
# ---------------------------------------------------------------------------------------------

def _chunk_study(fail=False):
    def study(checkpoint_dir, resume, shard):
        (checkpoint_dir / "chunk_000000.npz").write_bytes(b"a chunk")
        if fail:
            raise KeyboardInterrupt
        return {"done": True}
    return study


def _save(path, result):
    path.write_text("result")
    return path


def test_the_kept_chunks_of_a_finished_run_are_said_to_be_finished(tmp_path):
    from jaxsleigh.files.runner import run_to_file

    out = tmp_path / "o.npz"
    run_to_file(out, _chunk_study(), _save, options={"a": 1}, keep_chunks=True)
    with pytest.raises(ValueError, match="kept chunks of a finished run") as said:
        run_to_file(out, _chunk_study(), _save, options={"a": 1})
    assert "unfinished" not in str(said.value) and "resume=True" in str(said.value)
    # a run that starts there and is interrupted leaves an unfinished run's chunks, and is told so
    with pytest.raises(KeyboardInterrupt):
        run_to_file(out, _chunk_study(fail=True), _save, options={"a": 1}, resume=True, keep_chunks=True)
    with pytest.raises(ValueError, match="an earlier, unfinished run"):
        run_to_file(out, _chunk_study(), _save, options={"a": 1})


def test_the_command_line_tells_a_kept_finished_run_in_its_words(tmp_path, capsys):
    argv = ["optimum", "--samples", "1", "--horizons", "2", "--out", tmp_path / "o.npz", "--no-progress"]
    chunks = tmp_path / "o.npz.chunks"
    chunks.mkdir()
    (chunks / "chunk_000000.npz").write_bytes(b"a chunk")
    (chunks / "finished.json").write_text("{}")
    rc, _, err = run_cli(argv, capsys)
    assert rc == 2 and "kept chunks of a finished run" in err and "add --resume" in err, err


def test_resume_on_another_commands_chunks_says_so_in_one_line(tmp_path, capsys):
    import json

    chunks = tmp_path / "b.npz.chunks"
    chunks.mkdir()
    (chunks / "chunk_000000.npz").write_bytes(b"a chunk")
    recorded = {"command": "optimum", "samples": 16, "horizons": [5.0, 10.0], "p_tol": 0.001, "seed": 0,
                **{f"option_{i}": i for i in range(40)}}
    (chunks / "options.json").write_text(json.dumps(recorded))
    argv = ["basin", "--x", "1", "--y", "0.5", "--theta", "0.5", "--t-final", "0.1", "--no-progress", "--resume",
            "--out", tmp_path / "b.npz"]
    rc, _, err = run_cli(argv, capsys)
    assert rc == 2 and "holds the chunks of a 'jaxsleigh optimum' run, not of 'jaxsleigh basin'" in err, err
    assert "option_1" not in err and len(err.splitlines()) <= 2 and len(err) < 400, err


# ---------------------------------------------------------------------------------------------
# results print short
# ---------------------------------------------------------------------------------------------

def _optimum_result(S=300, H=12, N=40):
    rng = np.random.default_rng(0)
    return js.OptimumResult(starts=np.zeros((S, 5)), horizons=np.linspace(1.0, 12.0, H), eps=0.05,
                            energy=rng.random((S, H)), u=np.zeros((S, H, N, 2)), status=np.zeros((S, H), np.int32),
                            q_final=np.zeros((S, H, 3)), p_final=np.zeros((S, H, 2)), kkt=np.zeros((S, H)),
                            guess=np.zeros((S, H), np.int32))


def test_an_optimum_result_prints_its_summary_and_shapes_not_its_arrays():
    text = repr(_optimum_result())
    assert text.startswith("OptimumResult(3600 problems (300 starts x 12 horizons): 3600 converged"), text
    assert "u (300, 12, 40, 2)" in text and "eps = 0.05" in text and "T = 1: median E* = " in text
    assert "array(" not in text and "..., " not in text
    assert "... and 4 more horizons" in text and len(text.splitlines()) <= 13 and len(text) < 1000
    assert str(_optimum_result()) == text


def test_the_other_public_results_print_in_a_few_lines():
    n = 5000
    outs = [js.sample_starts(n, seed=1),
            js.SolveOutput(q_final=np.zeros((n, 3)), p_final=np.zeros((n, 2)), status=np.zeros(n, np.int32),
                           t_reached=np.zeros(n), n_steps=np.zeros(n), n_rejected=np.zeros(n),
                           summaries={"T_eps": np.zeros(n), "u_energy": np.zeros(n)}, Hd0=np.zeros(n))]
    for r in outs:
        assert len(repr(r)) < 2000 and len(repr(r).splitlines()) < 40, type(r).__name__


# ---------------------------------------------------------------------------------------------
# grammar
# ---------------------------------------------------------------------------------------------

def test_a_basin_file_given_as_an_optimum_file_says_an_optimum_file(tmp_path):
    np.savez(tmp_path / "x.npz", something=np.zeros(2))
    with pytest.raises(ValueError, match=r"is not an optimum file") as said:
        js.load_optimum(tmp_path / "x.npz")
    assert "a optimum" not in str(said.value)


def test_one_search_flag_belongs_to_search(tmp_path, capsys):
    rc, _, err = run_cli(["tune", "--steps", "1", "--population", "8", "--out", tmp_path / "g.json"], capsys)
    assert rc == 2 and "--population belongs to --search; add --search or drop it" in err, err
    rc, _, err = run_cli(["tune", "--steps", "1", "--population", "8", "--energy-margin", "0.9", "--out",
                          tmp_path / "g.json"], capsys)
    assert rc == 2 and "--population, --energy-margin belong to --search; add --search or drop them" in err, err


def test_a_map_of_sampled_starts_is_refused_in_plain_words():
    from jaxsleigh.plots.basin import _check_map

    class Result:
        starts = js.BasinStarts(np.zeros((2, 3)), "array", (2,), (), {})

    with pytest.raises(ValueError, match="these starts are an array varying no grid axis"):
        _check_map(Result(), "T_eps")


# ---------------------------------------------------------------------------------------------
# no code, test or page names an issue number
# ---------------------------------------------------------------------------------------------

#: An issue's number ("issue" and a number, "issue" and a number in a name, or "#" and a number after a space or an
#: opening bracket): a number of the project's tracker, which a reader cannot look up.
ISSUE_NUMBER = r"\bissues?\s*#?\s*\d|\bissue_?\d|(?<=[\s(\[])#\d+\b"


def test_no_code_test_or_page_names_an_issue_number():
    import re

    n = "12"                                   # put together: this file names no issue number itself
    assert re.search(ISSUE_NUMBER, f"see issue {n}", re.I) and re.search(ISSUE_NUMBER, f"fixed (#{n})", re.I)
    assert re.search(ISSUE_NUMBER, "exp" + f"eriments/issue{n}_x.py", re.I)
    assert not re.search(ISSUE_NUMBER, 'color="#333", "&#39;", tissue 3', re.I)
    found = []
    for folder in ("jaxsleigh", "tests", "docs", "experiments", "notebooks"):
        for path in sorted((ROOT / folder).rglob("*")):
            if path.suffix not in (".py", ".md", ".ipynb", ".txt", ".yml", ".toml", ".cfg") or not path.is_file():
                continue
            text = path.read_text(errors="replace")
            found += [f"{path.relative_to(ROOT)}:{text.count(chr(10), 0, m.start()) + 1}: {m.group(0)!r}"
                      for m in re.finditer(ISSUE_NUMBER, text, re.I)]
    for name in ("README.md", "CHANGELOG.md", "pyproject.toml", "mkdocs.yml"):
        found += [f"{name}: {m.group(0)!r}" for m in re.finditer(ISSUE_NUMBER, (ROOT / name).read_text(), re.I)]
    assert not found, "issue numbers named:\n" + "\n".join(found)


# ---------------------------------------------------------------------------------------------
# the times a reader is told: measured, with the machine named
# ---------------------------------------------------------------------------------------------

MACHINE = "2-core x86_64 machine"


def test_the_readme_times_are_the_measured_ones_with_the_machine_named():
    text = " ".join((ROOT / "README.md").read_text().split())
    # the quick tier, the comparison at equal energy, the Python example: measured with an empty compilation cache
    # (each measured by experiments/performance/fresh_machine.py, which writes docs/figures/fresh_machine.json)
    assert f"19-23 min on a {MACHINE}, empty compilation cache" in text
    assert "quick tier for every change (2 min 30 s there; both timed from a fresh clone" in text
    assert f"float32; 90 s on a {MACHINE}, empty compilation cache)" in text
    assert "(this example: 40 s cold, 2-core x86_64)" in text
    for stale in ("about 3 min cold", "2-core x86_64, about a minute"):
        assert stale not in text, stale


def test_the_command_line_tour_times_the_readme_basin():
    text = " ".join((ROOT / "docs" / "how-to" / "command-line.md").read_text().split())
    assert f"took 25 s on a {MACHINE} with an empty compilation cache" in text
    assert "others take seconds" not in text
    readme = (ROOT / "README.md").read_text()
    assert "jaxsleigh basin --x -3:3:32 --y -3:3:32 --theta 0.5 --t-final 100" in readme   # the basin timed


def test_a_tuning_run_with_the_same_options_is_told_the_same_run_is_in_progress(tmp_path, holder):
    from jaxsleigh.errors import RunLockedError
    from jaxsleigh.tuning.runs import TuningRun

    out = tmp_path / "g.json"
    first = TuningRun(out, options={"steps": 4, "seed": 1})
    assert first.run_id == TuningRun(out, options={"steps": 4, "seed": 1}).run_id
    assert first.run_id != TuningRun(out, options={"steps": 8, "seed": 1}).run_id
    holder(out, first.run_id)
    with pytest.raises(RunLockedError, match="the same run is in progress"):
        with TuningRun(out, options={"steps": 4, "seed": 1}).owned("tuning", checkpointed=False):
            pytest.fail("claimed an output the same run holds")
    with pytest.raises(RunLockedError, match="other settings"):
        with TuningRun(out, options={"steps": 8, "seed": 1}).owned("tuning", checkpointed=False):
            pytest.fail("claimed an output another run holds")
