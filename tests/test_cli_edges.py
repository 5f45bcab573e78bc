"""The command line's rough edges: summary lines that say what settled, refusals that name the flag, result
files checked field by field, figures written atomically, messages in the command line's own terms."""
from __future__ import annotations

import errno
import json

import numpy as np
import pytest

from jaxsleigh import cli


def run_cli(argv, capsys):
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return rc, out, err


# a short sampled run of a literature law that does not settle in 2 s, and a paper-law run that does not either
SAMPLED = ["simulate", "--ic", "1,1,0.5", "--controller", "astolfi", "--saturation", "2", "--sample-period", "0.05",
           "--t-final", "2"]
BASIN = ["basin", "--x", "1", "--y", "0.5:1:2", "--theta", "0.5", "--t-final", "2", "--dt", "0.05", "--method", "rk4",
         "--no-progress"]


# ---------------------------------------------------------------------------------------------
# summary lines: integrated is not settled
# ---------------------------------------------------------------------------------------------

def test_simulate_says_a_run_integrated_to_the_horizon_did_not_settle(tmp_path, capsys):
    rc, out, err = run_cli(SAMPLED + ["--out", tmp_path / "r.npz"], capsys)
    assert rc == 0, err
    assert "1 trajectory: 1 integrated; 0 settled (T_0.05 = inf)" in out, out
    assert " ok" not in out


def test_status_line_gives_the_median_settling_time_of_the_settled():
    from jaxsleigh.cli.common import status_line

    status = np.array([0, 0, 0, 1])
    T = np.array([1.0, 3.0, np.inf, np.nan])
    assert status_line(status, T, 0.1) == ("4 trajectories: 3 integrated, 1 singular_start; "
                                           "2 settled (median T_0.1 = 2 s)")
    assert status_line(status[:1], T[:1], 0.05).endswith("1 settled (T_0.05 = 1 s)")
    assert status_line(status[2:3], T[2:3], 0.05).endswith("0 settled (T_0.05 = inf)")


def test_basin_and_sweep_summaries_count_the_settled(tmp_path, capsys):
    rc, out, err = run_cli(BASIN + ["--eps", "0.3", "--out", tmp_path / "b.npz"], capsys)
    assert rc == 0, err
    assert "jaxsleigh basin: 2 trajectories: 2 integrated; 0 settled (T_0.3 = inf for all)" in out, out
    rc, out, err = run_cli(["sweep", "--param", "k=0.1:0.2:2"] + BASIN[1:] + ["--out", tmp_path / "s.npz"], capsys)
    assert rc == 0, err
    assert "2 values x 2 starts, 4 trajectories: 4 integrated; " in out and "settled" in out, out


# ---------------------------------------------------------------------------------------------
# the digital controller's options against the horizon
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("delay", ["40", "1000000000"])
def test_a_delay_as_long_as_the_horizon_is_refused_up_front(tmp_path, capsys, delay):
    rc, out, err = run_cli(SAMPLED + ["--delay", delay, "--out", tmp_path / "r.npz"], capsys)
    assert rc == 2 and f"--delay {delay} " in err and "holds 40 samples" in err and "below 40" in err, err
    assert not (tmp_path / "r.npz").exists()


def test_save_every_with_a_sample_period_is_refused_not_ignored(tmp_path, capsys):
    rc, out, err = run_cli(SAMPLED + ["--save-every", "5", "--out", tmp_path / "r.npz"], capsys)
    assert rc == 2 and "--save-every 5" in err and "every sample instant" in err, err


# ---------------------------------------------------------------------------------------------
# result files: every field checked, the file and the field named
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def basin_file(tmp_path_factory):
    """A tiny basin result written by the library (no command line): its arrays, to be damaged one at a time."""
    import jaxsleigh as js

    res = js.run_basin(np.array([[1.0, 1.0, 0.5], [1.0, 0.5, 0.5]]), t_final=0.5, dt=0.05,
                       stepsize=js.StepSizeController(method="rk4"), run=js.RunOptions(progress=False))
    path = js.save_basin(tmp_path_factory.mktemp("basin") / "b.npz", res)
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _damaged(tmp_path, arrays, **changes):
    path = tmp_path / "damaged.npz"
    np.savez(path, **{**arrays, **changes})
    return path


@pytest.mark.parametrize("change, field, words", [
    ({"T_eps": np.array(["1.0", "inf"])}, "T_eps", "real numbers"),
    ({"status": np.array([0.0, 0.0])}, "status", "whole numbers"),
    ({"T_eps": np.array([1.0])}, "T_eps", "shape (1,)"),
    ({"q_final": np.zeros((2, 2))}, "q_final", "expected (N, 3)"),
    ({"format_version": np.array("two")}, "format_version", "whole number"),
    ({"format_version": np.float64(2.0)}, "format_version", "whole number"),
])
def test_load_basin_names_the_file_and_the_damaged_field(tmp_path, basin_file, change, field, words):
    import jaxsleigh as js

    path = _damaged(tmp_path, basin_file, **change)
    with pytest.raises(ValueError) as e:
        js.load_basin(path)
    msg = str(e.value)
    assert str(path) in msg and f"field {field}" in msg and words in msg, msg


def test_an_undamaged_basin_file_still_loads(tmp_path, basin_file):
    import jaxsleigh as js

    back = js.load_basin(_damaged(tmp_path, basin_file))
    np.testing.assert_array_equal(back.T_eps, basin_file["T_eps"])


# ---------------------------------------------------------------------------------------------
# figures are written as the data files are
# ---------------------------------------------------------------------------------------------

def test_a_full_disk_while_drawing_leaves_no_truncated_figure_and_names_it(tmp_path, capsys, monkeypatch):
    from matplotlib.figure import Figure

    def full(self, f, **kw):
        f.write(b"\x89PNG\r\n\x1a\n half a figure")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Figure, "savefig", full)
    png = tmp_path / "map.png"
    rc, out, err = run_cli(BASIN + ["--out", tmp_path / "b.npz", "--plot", png], capsys)
    assert rc == 4 and str(png) in err and "no space left" in err, err
    assert not png.exists() and not list(tmp_path.glob(".map.png*"))
    # the chunks stay for --resume, which draws the figure once there is space
    assert "--resume" in err and (tmp_path / "b.npz.chunks").is_dir()
    monkeypatch.undo()
    rc, out, err = run_cli(BASIN + ["--out", tmp_path / "b.npz", "--plot", png, "--resume"], capsys)
    assert rc == 0 and png.read_bytes()[:4] == b"\x89PNG", err


# ---------------------------------------------------------------------------------------------
# sweeping a literature law's own parameters
# ---------------------------------------------------------------------------------------------

SWEEP_LAW = ["sweep", "--controller", "astolfi", "--x", "1", "--y", "1", "--theta", "0.5", "--t-final", "1", "--dt",
             "0.05", "--method", "rk4", "--no-progress"]


def test_sweep_sets_a_parameter_of_a_literature_law(tmp_path, capsys):
    rc, out, err = run_cli(SWEEP_LAW + ["--param", "K=1:8:2", "--out", tmp_path / "K.npz"], capsys)
    assert rc == 0, err
    with np.load(tmp_path / "K.npz") as z:
        assert z["names"].tolist() == ["K"] and z["values"][:, 0].tolist() == [1.0, 8.0]
        energy = z["u_energy"][:, 0]
    assert np.all(np.isfinite(energy)) and energy[0] != energy[1]       # the law ran with each value


def test_sweep_sets_a_literature_law_s_own_k_and_reads_the_file_back(tmp_path, capsys):
    """Astolfi's heading rate is named k like the paper's gain: it was refused as "a gain of the paper's law"."""
    import jaxsleigh as js

    rc, out, err = run_cli(SWEEP_LAW + ["--param", "k=0.5:2:2", "--out", tmp_path / "k.npz"], capsys)
    assert rc == 0, err
    back = js.load_sweep(tmp_path / "k.npz")
    assert back.names == ("k",) and back.values[:, 0].tolist() == [0.5, 2.0]
    assert back.axes[0].name == "k" and back.u_energy[0, 0] != back.u_energy[1, 0]


@pytest.mark.parametrize("param", ["l1=1:2:2", "gain=1:2:2"])
def test_sweep_lists_what_the_controller_really_lets_one_sweep(tmp_path, capsys, param):
    rc, out, err = run_cli(SWEEP_LAW + ["--param", param, "--out", tmp_path / "x.npz"], capsys)
    assert rc == 2 and f"--param {param}" in err and "under --controller astolfi" in err, err
    allowed = err.split("choose one of ", 1)[1].split(" (e.g.")[0].split(", ")
    assert {"K", "p2", "p3", "m", "J", "l", "coulomb_eps"} <= set(allowed), err
    assert not {"l1", "d11", "d22"} & set(allowed), err


# ---------------------------------------------------------------------------------------------
# bounds that do not fit, the controllers' list, the help's cache folder
# ---------------------------------------------------------------------------------------------

def test_a_saturation_bound_beyond_float32_is_refused_with_the_way_on(tmp_path, capsys):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")                  # no "overflow encountered in cast" on the way
        rc, out, err = run_cli(["simulate", "--ic", "1,1,0.5", "--saturation", "1e300", "--out", tmp_path / "r.npz"],
                               capsys)
    assert rc == 2 and "--saturation 1e+300" in err and "float32" in err and "3.4e+38" in err and "--x64" in err, err
    assert "overflow" not in err and not (tmp_path / "r.npz").exists()


def test_the_controllers_list_says_in_words_what_a_law_knows_of_the_plant(capsys):
    from jaxsleigh.controllers.registry import CONTROLLERS, controller_class

    rc, out, err = run_cli(["controllers"], capsys)
    lines = out.strip().splitlines()
    assert rc == 0 and len(lines) == len(CONTROLLERS) and "needs nothing" not in out
    for name, line in zip(CONTROLLERS, lines):
        if controller_class(name).needs:
            assert "needs a model of the plant (m, J, l, damping)" in line, line
        else:
            assert "reads only q and v" in line, line
    assert out.endswith("\n") and err.startswith("jaxsleigh controllers: ")     # the wall line on its own


def test_the_help_names_the_cache_folder_this_environment_uses(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("JAXSLEIGH_CACHE_DIR", raising=False)
    monkeypatch.delenv("JAXSLEIGH_NO_COMPILE_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    help_text = cli.build_parser().format_help()
    assert f"cached in {tmp_path / 'xdg' / 'jaxsleigh' / 'jax'}" in help_text and "~/.cache" not in help_text
    monkeypatch.setenv("JAXSLEIGH_NO_COMPILE_CACHE", "1")
    assert "not cached" in cli.build_parser().format_help()


# ---------------------------------------------------------------------------------------------
# tables of starts with a header line
# ---------------------------------------------------------------------------------------------

def test_a_csv_of_starts_may_begin_with_a_header_line(tmp_path, capsys):
    csv = tmp_path / "starts.csv"
    csv.write_text("x,y,theta\n1,1,0.5\n-1,2,1\n")
    rc, out, err = run_cli(["simulate", "--ics", csv, "--t-final", "1", "--method", "rk4", "--out",
                            tmp_path / "r.npz"], capsys)
    assert rc == 0 and "2 trajectories: 2 integrated" in out, err
    with np.load(tmp_path / "r.npz") as z:
        np.testing.assert_array_equal(z["ics"][:, :3], [[1, 1, 0.5], [-1, 2, 1]])


def test_a_table_that_is_not_numbers_gets_advice_about_tables_not_numpy(tmp_path):
    from jaxsleigh.files.npz import load_ics

    csv = tmp_path / "starts.csv"
    csv.write_text("x,y,theta\n1,1,0.5\nfoo,2,1\n")
    with pytest.raises(ValueError) as e:
        load_ics(csv)
    assert str(csv) in str(e.value) and "header line" in str(e.value) and "numpy" not in str(e.value)
