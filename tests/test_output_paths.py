"""Outputs are written to regular files only: a path that is a folder, a device, a named pipe (FIFO) or a
socket, also once the library appends its ``.npz``, is refused before any work, with a message that names the
path and what it is; nothing there is opened, written or replaced.

The devices are links to ``/dev/null`` inside the test's folder: a check that only looks (``stat``) refuses them,
and a writer that renamed its file into place would replace the link, never the device.
"""
from __future__ import annotations

import importlib
import os
import re
import stat

import pytest

import jaxsleigh as js
from jaxsleigh import cli

#: Words the refusal uses for each kind of path.
WORDS = {"folder": "is a folder", "fifo": "is a named pipe (FIFO), not a regular file",
         "device": "is a character device, not a regular file"}


def make(path, kind):
    """Make ``path`` a folder, a named pipe, or a link to the character device /dev/null."""
    if kind == "folder":
        path.mkdir()
    elif kind == "fifo":
        os.mkfifo(path)
    else:
        path.symlink_to("/dev/null")
    return path


def untouched(path, kind):
    """``path`` is still what `make` made (nothing replaced it)."""
    mode = os.stat(path).st_mode
    return {"folder": stat.S_ISDIR, "fifo": stat.S_ISFIFO, "device": stat.S_ISCHR}[kind](mode)


@pytest.fixture
def no_work(monkeypatch):
    """Every command's first piece of work fails the test: the refusal must come before it."""
    def work(*a, **k):
        raise AssertionError("work started before the outputs were checked")

    for mod, name in [("jaxsleigh.studies.simulate", "drive_saving"), ("jaxsleigh.studies.ensemble", "drive_final"),
                      ("jaxsleigh.tuning.optimizer", "make_training_set"), ("jaxsleigh.studies.compare", "compare"),
                      ("jaxsleigh.studies.compare", "draw_compare_starts"),
                      ("jaxsleigh.tuning.budget", "tune_to_budget"), ("jaxsleigh.plots.paper_run", "simulate")]:
        monkeypatch.setattr(importlib.import_module(mod), name, work)


def run_cli(argv, capsys):
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return rc, out, err


COMMANDS = {
    "simulate": ["simulate", "--ic", "1,1,0.5", "--t-final", "0.1"],
    "compare": ["compare", "--controllers", "paper", "--starts", "near", "--samples", "2", "--t-final", "1"],
    "tune": ["tune", "--steps", "1", "--batch", "4", "--no-progress"],
    "basin": ["basin", "--x", "1", "--y", "0.5", "--theta", "0.5", "--t-final", "0.1", "--no-progress"],
}


@pytest.mark.parametrize("kind", ["folder", "fifo", "device"])
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_an_out_that_is_not_a_regular_file_is_refused_before_any_work(tmp_path, capsys, no_work, command, kind):
    name = {"simulate": "run.npz", "compare": "c.json", "tune": "g.json", "basin": "b.npz"}[command]
    target = make(tmp_path / name, kind)
    rc, out, err = run_cli(COMMANDS[command] + ["--out", target], capsys)
    assert rc == 2, (out, err)
    assert f"'{target}' {WORDS[kind]}" in err and "--out" in err, err
    assert "wrote" not in out
    assert untouched(target, kind)


@pytest.mark.parametrize("kind", ["folder", "fifo", "device"])
@pytest.mark.parametrize("command", ["simulate", "basin"])
def test_the_name_given_and_the_name_with_npz_appended_are_both_checked(tmp_path, capsys, no_work, command, kind):
    """``--out NAME``: NAME.npz is written, so NAME.npz must be a regular file; NAME itself being a device
    (``--out /dev/full``) is refused too, not written next to it as ``/dev/full.npz``."""
    given = make(tmp_path / "run", kind)
    rc, _, err = run_cli(COMMANDS[command] + ["--out", given], capsys)
    assert rc == 2 and f"'{given}' {WORDS[kind]}" in err, err
    assert not (tmp_path / "run.npz").exists()
    appended = make(tmp_path / "other.npz", kind)
    rc, _, err = run_cli(COMMANDS[command] + ["--out", tmp_path / "other"], capsys)
    assert rc == 2 and f"'{appended}' {WORDS[kind]}" in err, err


@pytest.mark.parametrize("kind", ["folder", "fifo", "device"])
def test_tune_refuses_a_history_that_is_not_a_regular_file(tmp_path, capsys, no_work, kind):
    history = make(tmp_path / "h.npz", kind)
    rc, _, err = run_cli(COMMANDS["tune"] + ["--out", tmp_path / "g.json", "--history", tmp_path / "h"], capsys)
    assert rc == 2 and f"'{history}' {WORDS[kind]}" in err, err


@pytest.mark.parametrize("kind", ["folder", "fifo", "device"])
def test_run_to_file_refuses_an_out_that_is_not_a_regular_file(tmp_path, kind):
    from jaxsleigh.files.runner import run_to_file

    def study(**kw):
        raise AssertionError("work started before the output was checked")

    target = make(tmp_path / "mc", kind)
    with pytest.raises(ValueError, match=re.escape(f"'{target}' {WORDS[kind]}")):
        run_to_file(target, study, js.save_basin)
    assert not (tmp_path / "mc.npz").exists() and not (tmp_path / "mc.chunks").exists()
    target = make(tmp_path / "other.npz", kind)
    with pytest.raises(ValueError, match=re.escape(f"'{target}' {WORDS[kind]}")):
        run_to_file(tmp_path / "other", study, js.save_basin)
    assert untouched(target, kind)


def test_run_to_file_refuses_a_folder_given_as_the_output(tmp_path):
    """``run_to_file("/tmp", ...)`` wrote ``/tmp.npz``; a folder is refused, whatever the suffix."""
    from jaxsleigh.files.runner import run_to_file

    with pytest.raises(ValueError, match="is a folder; give a file name"):
        run_to_file(tmp_path, lambda **kw: None, js.save_basin)
    assert not tmp_path.with_name(tmp_path.name + ".npz").exists()


@pytest.mark.parametrize("kind", ["folder", "fifo", "device"])
def test_tuning_run_refuses_an_out_that_is_not_a_regular_file(tmp_path, kind):
    from jaxsleigh.tuning.runs import TuningRun

    target = make(tmp_path / "g.json", kind)
    with pytest.raises(ValueError, match=re.escape(f"'{target}' {WORDS[kind]}")):
        with TuningRun(target).owned("tuning"):
            raise AssertionError("the output was claimed")
    assert untouched(target, kind)


@pytest.mark.parametrize("kind", ["folder", "fifo", "device"])
def test_every_writer_refuses_a_path_that_is_not_a_regular_file(tmp_path, kind):
    """The save_* functions and the atomic writer under them never replace a device, pipe or folder."""
    from jaxsleigh.files.npz import atomic_write_text, write_result
    from jaxsleigh.tuning.history import save_history

    target = make(tmp_path / "x.npz", kind)
    for write in (lambda: atomic_write_text(target, "{}"), lambda: write_result(tmp_path / "x", {}, {}),
                  lambda: save_history(None, tmp_path / "x"), lambda: js.save_gains(js.paper_gains(), target)):
        with pytest.raises(ValueError, match=re.escape(f"'{target}' {WORDS[kind]}")):
            write()
    assert untouched(target, kind)


def test_a_figure_output_that_is_a_named_pipe_is_refused(tmp_path, capsys, no_work):
    pipe = make(tmp_path / "b.png", "fifo")
    rc, _, err = run_cli(COMMANDS["basin"] + ["--out", tmp_path / "b.npz", "--plot", pipe], capsys)
    assert rc == 2 and f"--plot file '{pipe}' {WORDS['fifo']}" in err, err


def test_the_check_only_looks(tmp_path):
    from jaxsleigh.validate import not_a_file, output_file, writable_path

    pipe = make(tmp_path / "p", "fifo")
    assert not_a_file(pipe) == "a named pipe (FIFO)"        # a stat: an open would block here
    assert not_a_file(tmp_path / "absent") is None
    (tmp_path / "f").write_text("x")
    assert not_a_file(tmp_path / "f") is None
    assert output_file(tmp_path / "f", suffix=".npz") == tmp_path / "f.npz"
    assert writable_path(tmp_path / "new.npz") == tmp_path / "new.npz"
    import socket

    sock = socket.socket(socket.AF_UNIX)
    try:
        sock.bind(str(tmp_path / "s"))
        assert not_a_file(tmp_path / "s") == "a socket"
        with pytest.raises(ValueError, match="is a socket, not a regular file"):
            output_file(tmp_path / "s")
    finally:
        sock.close()
    if os.path.exists("/dev/full"):
        with pytest.raises(ValueError, match="'/dev/full' is a character device"):
            output_file("/dev/full", "--out file", suffix=".npz")


@pytest.mark.parametrize("kind", ["folder", "fifo", "device"])
def test_paper_refuses_a_figure_or_data_file_that_is_not_a_regular_file(tmp_path, capsys, no_work, kind):
    out = tmp_path / "paper"
    out.mkdir()
    target = make(out / "fig2_paths.png", kind)
    rc, _, err = run_cli(["paper", "--t-final", "1", "--out", out], capsys)
    assert rc == 2 and f"'{target}' {WORDS[kind]}" in err, err
    assert untouched(target, kind) and not (out / "paper.npz").exists()
