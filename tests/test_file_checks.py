"""Files read back are checked for content before they are used.

Every ``.npz`` jaxsleigh writes records a SHA-256 of its arrays (``__digest__``), verified on read; chunks, result
files, optimum files and tuner checkpoints are also checked for fields, dtypes, shapes and values. A damaged or edited
chunk is recomputed on resume (a `DamagedCheckpointWarning` names it) and the result is the uninterrupted run's, to the
byte; any other file is refused with a `DamagedFileError` naming it and what is wrong, which the command line prints
(exit code 2, no traceback).
"""
from __future__ import annotations

import io as _io
import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh import cli
from jaxsleigh.errors import DamagedCheckpointWarning, DamagedFileError

BASIN = ["--samples", "32", "--t-final", "0.3", "--dt", "0.05", "--chunk-size", "8", "--no-progress"]


def run_cli(argv, capsys):
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return rc, out, err


def _arrays(path) -> dict:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _rewrite(path, arrays: dict) -> None:
    """Write ``arrays`` over ``path`` as a user editing it with NumPy would (np.savez, every key given)."""
    buf = _io.BytesIO()
    np.savez(buf, **arrays)
    Path(path).write_bytes(buf.getvalue())


# ---------------------------------------------------------------------------------------------
# 1. a chunk edited by hand is recomputed, never used
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def basin_run(tmp_path_factory):
    """A basin run's chunks (kept) and the bytes of its result file."""
    base = tmp_path_factory.mktemp("basin")
    out = base / "b.npz"
    assert cli.main(["basin", *BASIN, "--out", str(out), "--keep-chunks"]) == 0
    return base / "b.npz.chunks", out.read_bytes()


def _settled(a):            # every start settled at 1 s: the edit of the user test
    return {**a, "T_eps": np.ones_like(a["T_eps"]), "status": np.zeros_like(a["status"])}


EDITS = {
    "values": _settled,
    "values, digest dropped": lambda a: {k: v for k, v in _settled(a).items() if k != "__digest__"},
    "status as float64": lambda a: {**a, "status": np.full(a["status"].shape, 0.5)},
    "T_eps as strings": lambda a: {**a, "T_eps": a["T_eps"].astype(str)},
    "unknown status code": lambda a: {**a, "status": np.full_like(a["status"], 99)},
}


@pytest.mark.parametrize("edit", list(EDITS))
def test_an_edited_basin_chunk_is_named_and_recomputed(tmp_path, capsys, basin_run, edit):
    chunks, fresh = basin_run
    out = tmp_path / "b.npz"
    shutil.copytree(chunks, tmp_path / "b.npz.chunks")
    chunk = tmp_path / "b.npz.chunks" / "chunk_000001.npz"
    _rewrite(chunk, EDITS[edit](_arrays(chunk)))
    rc, text, err = run_cli(["basin", *BASIN, "--out", out, "--resume"], capsys)
    assert rc == 0, err
    assert "chunk_000001.npz" in err and "recomputing it" in err, err
    assert "3 chunk(s) resumed" in text, text
    assert out.read_bytes() == fresh                     # the uninterrupted run's result, to the byte


def test_the_chunk_store_says_what_is_wrong_with_an_edited_chunk(tmp_path):
    from jaxsleigh.files.chunks import ChunkStore

    starts = np.arange(20.0).reshape(4, 5)
    s = ChunkStore(tmp_path / "ck", "k")
    s.open(resume=False, manifest={})
    try:
        good = {"T_eps": np.array([1.0, np.inf, np.nan, 0.5]), "status": np.array([0, 9, 1, 0], np.int32)}
        path = s.save(0, good, lo=0, starts=starts)
        assert s.load(0, 4, lo=0, starts=starts) is not None
        for arrays, words in (({**good, "status": np.array([0, 99, 1, 0], np.int32)}, "unknown status code.*99"),
                              ({**good, "status": np.array([0.0, 0.5, 1.0, 0.0])}, "status holds float64"),
                              ({**good, "T_eps": good["T_eps"].astype(str)}, "T_eps holds <U"),
                              ({**good, "T_eps": np.array([1.0, -1.0, 1.0, 1.0])}, "negative times")):
            s.save(0, arrays, lo=0, starts=starts)       # written by the store: a valid digest, bad values
            with pytest.warns(DamagedCheckpointWarning, match=words):
                assert s.load(0, 4, lo=0, starts=starts) is None
        s.save(0, good, lo=0, starts=starts)
        _rewrite(path, {**_arrays(path), "T_eps": np.ones(4)})
        with pytest.warns(DamagedCheckpointWarning, match=r"chunk_000000\.npz.*do not match the digest"):
            assert s.load(0, 4, lo=0, starts=starts) is None
    finally:
        s.close()


# ---------------------------------------------------------------------------------------------
# 2. result files: edited values, unknown status codes
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def basin_file(tmp_path_factory):
    res = js.run_basin(np.array([[1.0, 1.0, 0.5], [1.0, 0.5, 0.5]]), t_final=0.5, dt=0.05,
                       stepsize=js.StepSizeController(method="rk4"), run=js.RunOptions(progress=False))
    return _arrays(js.save_basin(tmp_path_factory.mktemp("basin") / "b.npz", res))


def test_a_result_file_edited_by_hand_is_refused_naming_it(tmp_path, basin_file, capsys):
    path = tmp_path / "b.npz"
    _rewrite(path, {**basin_file, "T_eps": np.ones(2), "status": np.zeros(2, np.int32)})
    with pytest.raises(DamagedFileError, match="do not match the digest") as e:
        js.load_basin(path)
    assert str(path) in str(e.value) and e.value.path is not None
    _rewrite(path, basin_file)                          # rewritten unchanged: still loads
    np.testing.assert_array_equal(js.load_basin(path).T_eps, basin_file["T_eps"])


def test_an_unknown_status_code_in_a_result_file_names_the_file(tmp_path, basin_file):
    path = tmp_path / "b.npz"
    _rewrite(path, {**basin_file, "status": np.array([99, 0], np.int32)})
    with pytest.raises(DamagedFileError) as e:
        js.load_basin(path)
    assert str(path) in str(e.value) and "unknown status code" in str(e.value) and "99" in str(e.value)


@pytest.mark.parametrize("kind, status", [("sweep", np.array([[0, 99]], np.int32)),
                                          ("simulation", np.array([0, -1], np.int32)),
                                          ("basin", np.array([0.0, 1.0]))])
def test_every_result_kind_checks_its_status_codes(tmp_path, kind, status):
    from jaxsleigh.files.npz import check_fields

    with pytest.raises(DamagedFileError) as e:
        check_fields(tmp_path / "r.npz", {"status": status}, kind)
    assert "r.npz" in str(e.value) and "status" in e.value.problem


# ---------------------------------------------------------------------------------------------
# 3. tuner checkpoints: a missing field, NaN parameters, a huge counter
# ---------------------------------------------------------------------------------------------

def _tuner(tmp_path):
    from jaxsleigh import tuning as tu
    from jaxsleigh.tuning.checkpoint import Checkpoint, TunerCheckpoint, tune_settings
    from jaxsleigh.tuning.optimizer import CandidateTrack

    stamp = Checkpoint.of_run(tune_settings(js.gains(), ("k",), tu.TuneConfig(steps=4), tu.LossConfig(), None, None, None,
                                       False, 0.0, None), js.sample_starts(4, seed=1).ics)
    path = tmp_path / "t.ckpt.npz"
    TunerCheckpoint(path, stamp, ("loss",)).save(2, {"k": np.ones(1)}, (), CandidateTrack(0.0, False))

    def load():
        return TunerCheckpoint(path, stamp, ("loss",)).load({"k": np.zeros(1)}, (), [], CandidateTrack(0.0, False),
                                                            budget=4)
    return path, load


CHECKPOINT_EDITS = {
    "missing field": (lambda a: {k: v for k, v in a.items() if k != "scalar/multiplier"}, "scalar/multiplier"),
    "NaN parameters": (lambda a: {**a, "trainable/0": np.full(1, np.nan)}, "not all finite"),
    "huge iteration counter": (lambda a: {**a, "it": np.int64(10 ** 9)}, "1000000000, outside 0-4"),
    "parameters as strings": (lambda a: {**a, "trainable/0": np.array(["1.0"])}, "not numbers"),
}


@pytest.mark.parametrize("edit", list(CHECKPOINT_EDITS))
@pytest.mark.parametrize("digest", ["kept", "dropped"])
def test_an_edited_tuner_checkpoint_is_refused_naming_it(tmp_path, edit, digest):
    path, load = _tuner(tmp_path)
    assert load()[0] == 2
    change, words = CHECKPOINT_EDITS[edit]
    arrays = change(_arrays(path))
    if digest == "dropped":                    # without its digest the field checks still catch it
        arrays.pop("__digest__", None)
    _rewrite(path, arrays)
    with pytest.raises(DamagedFileError) as e:
        load()
    msg = str(e.value)
    assert str(path) in msg and "delete it and start afresh" in msg, msg
    assert ("do not match the digest" if digest == "kept" else words) in msg, msg


def test_an_edited_law_checkpoint_is_refused_naming_it(tmp_path):
    import jax.numpy as jnp
    import optax

    from jaxsleigh.tuning.checkpoint import LawCheckpoint, Checkpoint

    stamp = Checkpoint.of("k", {"law": "x"})
    path = tmp_path / "law.ckpt.npz"
    params = jnp.ones(3)
    opt = optax.adam(0.1)
    hist = {"loss": [1.0, 0.5], "energy": [2.0, 1.5], "valid": [True, True]}
    LawCheckpoint(path, stamp).save(2, params, opt.init(params), (params, 0.5, 1.5), hist, False)
    assert LawCheckpoint(path, stamp).load(params, opt.init(params))[0] == 2
    for change, words in (({"params": np.array([1.0, np.nan, 1.0])}, "not all finite"),
                          ({"it": np.int64(10 ** 9)}, "outside 0-2")):
        arrays = {k: v for k, v in _arrays(path).items() if k != "__digest__"}
        _rewrite(path, {**arrays, **change})
        with pytest.raises(DamagedFileError, match=words) as e:
            LawCheckpoint(path, stamp).load(params, opt.init(params))
        assert str(path) in str(e.value)
        LawCheckpoint(path, stamp).save(2, params, opt.init(params), (params, 0.5, 1.5), hist, False)


# ---------------------------------------------------------------------------------------------
# 4. optimum files and frontiers
# ---------------------------------------------------------------------------------------------

def _optimum(horizons=(5.0, 10.0)):
    from jaxsleigh.studies.optimum import OptimumResult, OptimumStatus

    S, H = 2, len(horizons)
    h = np.asarray(horizons, float)
    return OptimumResult(starts=np.ones((S, 5)), horizons=h, eps=0.05, energy=np.ones((S, H)) / h ** 2,
                         u=np.zeros((S, H, 2, 2)), status=np.full((S, H), OptimumStatus.CONVERGED, np.int32),
                         q_final=np.zeros((S, H, 3)), p_final=np.zeros((S, H, 2)), kkt=np.zeros((S, H)),
                         guess=np.zeros((S, H), np.int32))


def test_an_optimum_file_with_text_for_energy_is_refused_naming_it(tmp_path):
    from jaxsleigh.studies.optimum import load_optimum, save_optimum

    path = save_optimum(tmp_path / "o.npz", _optimum())
    assert load_optimum(path).energy.shape == (2, 2)
    a = _arrays(path)
    _rewrite(path, {**a, "energy": a["energy"].astype(str)})
    with pytest.raises(DamagedFileError, match="field energy must hold real numbers") as e:
        load_optimum(path)
    assert str(path) in str(e.value)
    _rewrite(path, {**a, "status": np.full((2, 2), 7, np.int32)})
    with pytest.raises(DamagedFileError, match="unknown status code"):
        load_optimum(path)


def test_an_optimum_file_with_decreasing_horizons_is_refused_as_the_command_line_refuses_them(tmp_path, capsys):
    from jaxsleigh.studies.optimum import load_optimum, save_optimum

    path = save_optimum(tmp_path / "o.npz", _optimum((10.0, 5.0)))     # the writer is not the one checking
    with pytest.raises(DamagedFileError, match=r"horizons must be finite, > 0 and strictly increasing") as e:
        load_optimum(path)
    assert str(path) in str(e.value)
    rc, _, err = run_cli(["optimum", "--horizons", "10,5", "--out", tmp_path / "x.npz"], capsys)
    assert rc == 2 and "increase" in err, err


def test_a_json_file_given_as_a_frontier_is_named_and_not_an_npz(tmp_path, capsys):
    front = tmp_path / "front.json"
    front.write_text(json.dumps({"horizons": [5, 10]}))
    rc, _, err = run_cli(["tune", "--search", "--out", tmp_path / "h.json", "--frontier", front], capsys)
    assert rc == 2, err
    assert str(front) in err and "JSON file, not an .npz" in err and "optimum file" in err, err
    assert "allow_pickle" not in err, err
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(DamagedFileError, match="not an .npz"):
            js.load_optimum(front)
