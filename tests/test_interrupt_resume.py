"""One run lifecycle for every command that writes: Ctrl-C after the first chunk (or iteration) of every chunked
command and every tuner mode keeps the finished work, and ``--resume`` ends with the bytes of an uninterrupted run.
While a chunked run works it holds one lock (next to its output, covering its chunk folder) and its chunk folder one
record file (``manifest.json``: the chunk store's fields and the command's options)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from jaxsleigh.cli import main as cli_main
from jaxsleigh.cli.common import EXIT_INTERRUPTED
from jaxsleigh.files.chunks import ChunkStore

#: the smallest run of every chunked command, in two chunks or more
CHUNKED = {
    "basin": ["basin", "--x", "-2:2:3", "--y", "-1:1:2", "--theta", "0.9", "--eps", "0.31", "--t-final", "5",
              "--dt", "0.05", "--method", "rk4", "--chunk-size", "3", "--no-progress"],
    "sweep": ["sweep", "--param", "k=0.05:0.4:2:log", "--samples", "4", "--seed", "3", "--x", "-1:1", "--y", "-1:1",
              "--theta", "0.3:1.5", "--eps", "0.2", "--t-final", "5", "--dt", "0.05", "--chunk-size", "4",
              "--no-progress"],
    "optimum": ["optimum", "--samples", "2", "--seed", "3", "--horizons", "10", "--intervals", "8", "--chunk-size", "1",
                "--no-progress"],
}


def _run(argv, capsys):
    rc = cli_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _locks(root: Path) -> list:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if ".lock." in p.name)


@pytest.mark.parametrize("command", sorted(CHUNKED))
def test_every_chunked_command_resumes_to_the_bytes_of_an_uninterrupted_run(tmp_path, capsys, monkeypatch, command):
    argv = CHUNKED[command]
    real, seen, saved = ChunkStore.save, {}, []

    def counted(self, *a, **k):
        saved.append(1)
        return real(self, *a, **k)

    whole = tmp_path / "whole.npz"
    with monkeypatch.context() as m:
        m.setattr(ChunkStore, "save", counted)
        rc, _, err = _run([*argv, "--out", whole], capsys)
    assert rc == 0 and len(saved) >= 2, err
    total = len(saved)
    out = tmp_path / "out.npz"
    chunks = tmp_path / "out.npz.chunks"

    def save(self, *a, **k):                       # Ctrl-C once the first chunk is written
        real(self, *a, **k)
        seen["locks"] = _locks(tmp_path)
        seen["record"] = json.loads((chunks / "manifest.json").read_text())
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(ChunkStore, "save", save)
        rc, _, err = _run([*argv, "--out", out], capsys)
    assert rc == EXIT_INTERRUPTED and "--resume" in err and not out.exists(), err
    assert seen["locks"] == [f".out.npz.lock.{seen['locks'][0].rsplit('.lock.', 1)[1]}"], seen["locks"]  # one lock
    record = seen["record"]
    assert {"key", "options"} <= set(record) and record["options"]["command"] == command, record
    assert sorted(p.name for p in chunks.iterdir()) == ["chunk_000000.npz", "manifest.json"]   # one record file
    assert _locks(tmp_path) == []
    rc, _, err = _run([*argv, "--out", out], capsys)                     # never over the chunks, silently
    assert rc == 2 and "--resume" in err, err
    saved.clear()
    with monkeypatch.context() as m:
        m.setattr(ChunkStore, "save", counted)
        rc, _, err = _run([*argv, "--out", out, "--resume"], capsys)
    assert rc == 0 and len(saved) == total - 1, err                     # the first chunk is not computed again
    assert out.read_bytes() == whole.read_bytes() and not chunks.exists() and _locks(tmp_path) == []


def test_a_refused_resume_names_the_option_from_the_one_record_and_an_old_options_file_is_read(tmp_path, capsys):
    argv = CHUNKED["basin"]
    out = tmp_path / "b.npz"
    assert _run([*argv, "--out", out, "--keep-chunks"], capsys)[0] == 0
    chunks = tmp_path / "b.npz.chunks"
    assert not (chunks / "options.json").exists()
    out.unlink()
    rc, _, err = _run([*argv[:-1], "--eps", "0.2", "--no-progress", "--out", out, "--resume"], capsys)
    assert rc == 2 and "--eps 0.31 in the checkpoint vs --eps 0.2 now" in err, err
    # a folder of jaxsleigh 0.3 kept its options in options.json: still named
    record = json.loads((chunks / "manifest.json").read_text())
    (chunks / "options.json").write_text(json.dumps(record.pop("options")))
    (chunks / "manifest.json").write_text(json.dumps(record))
    rc, _, err = _run([*argv[:-1], "--eps", "0.2", "--no-progress", "--out", out, "--resume"], capsys)
    assert rc == 2 and "--eps 0.31 in the checkpoint vs --eps 0.2 now" in err, err


# ---------------------------------------------------------------------------------------------
# every tuner mode: Ctrl-C after its first iterations, --resume to an uninterrupted run's files
# ---------------------------------------------------------------------------------------------

GRADIENT = ["tune", "--steps", "3", "--batch", "4", "--t-final", "5", "--n-attempts", "2000", "--tune", "k",
            "--validate", "0", "--no-progress"]
SEARCH = ["tune", "--search", "--steps", "3", "--batch", "8", "--population", "4", "--validate", "0", "--no-progress"]
FRONT = ["tune", "--pareto", "2", "--steps", "2", "--warm-steps", "1", "--batch", "4", "--t-final", "10",
         "--n-attempts", "1500", "--tune", "L,k", "--validate", "0", "--budgets", "5:50", "--no-progress"]
FRONT_VMAP = ["tune", "--pareto", "2", "--front-method", "vmap", "--steps", "3", "--batch", "4", "--t-final", "10",
              "--n-attempts", "1500", "--tune", "L,k", "--validate", "0", "--budgets", "5:50", "--no-progress"]
LAW = ["tune", "--controller", "astolfi", "--steps", "3", "--batch", "2", "--t-final", "2", "--validate", "0",
       "--no-progress"]

#: what differs between two runs of the same settings: when they ran and how they were called
VOLATILE = {"wall_s", "command"}


def _after_calls(module, name, n):
    """An interrupter: Ctrl-C in the ``n``-th call of ``module.name`` (the earlier ones done and checkpointed)."""
    def arm(m):
        real, calls = getattr(module, name), []

        def f(*a, **k):
            calls.append(1)
            if len(calls) == n:
                raise KeyboardInterrupt
            return real(*a, **k)
        m.setattr(module, name, f)
    return arm


def _gradient(m):
    from jaxsleigh.tuning import optimizer

    real = optimizer._Bar.update

    def update(self, it, row):
        real(self, it, row)
        if it == 1:
            raise KeyboardInterrupt
    m.setattr(optimizer._Bar, "update", update)


def _law(m):
    from jaxsleigh.tuning import law

    real = law._Descent._step

    def step(self, step_fn, it, *rest):
        if it == 2:
            raise KeyboardInterrupt
        return real(self, step_fn, it, *rest)
    m.setattr(law._Descent, "_step", step)


def _search(m):
    from jaxsleigh.tuning import cma_search

    _after_calls(cma_search, "evaluate_population", 4)(m)


def _front(m):
    from jaxsleigh.tuning import pareto

    _after_calls(pareto, "tune", 2)(m)


def _front_vmap(m):
    from jaxsleigh.tuning import pareto

    _after_calls(pareto, "_assess_candidates", 3)(m)


#: mode -> (argv, interrupter, writes a history, the history's fields that hold wall time, what Ctrl-C says)
TUNERS = {"gradient": (GRADIENT, _gradient, True, ("wall",), "interrupted after 2 iterations"),
          "search": (SEARCH, _search, True, ("wall_s",), "interrupted after 2 generations"),
          "law": (LAW, _law, True, (), "interrupted after 2 steps"),
          "front": (FRONT, _front, False, (), "interrupted after 1 of 2 points"),
          "front-vmap": (FRONT_VMAP, _front_vmap, False, (), "interrupted after 2 of 3 iterations; wrote the best "
                                                             "candidate so far of 2 of 2 budgets")}


def _doc(path) -> dict:
    def strip(d):
        return {k: strip(v) if isinstance(v, dict) else v for k, v in d.items() if k not in VOLATILE}

    return strip(json.loads(Path(path).read_text()))


@pytest.mark.slow
@pytest.mark.parametrize("mode", sorted(TUNERS))
def test_every_tuner_mode_resumes_to_the_files_of_an_uninterrupted_run(tmp_path, capsys, mode):
    argv, interrupt, history, wall, says = TUNERS[mode]
    hist = (lambda p: ["--history", p.with_suffix(".npz")]) if history else (lambda p: [])
    whole, out = tmp_path / "whole.json", tmp_path / "out.json"
    rc, _, err = _run([*argv, "--out", whole, *hist(whole)], capsys)
    assert rc == 0, err
    with pytest.MonkeyPatch.context() as m:
        interrupt(m)
        rc, _, err = _run([*argv, "--out", out, *hist(out)], capsys)
    assert rc == EXIT_INTERRUPTED and "--resume" in err and says in err, err
    kept = json.loads(out.read_text())                                       # the best so far, flagged
    assert kept.get("interrupted", kept.get("meta", {}).get("interrupted")) is True
    assert _locks(tmp_path) == []
    rc, _, err = _run([*argv, "--out", out, *hist(out)], capsys)              # never over the progress, silently
    assert rc == 2 and "--resume" in err, err
    rc, _, err = _run([*argv, "--out", out, *hist(out), "--resume"], capsys)
    assert rc == 0, err
    a = _doc(out)
    assert _doc(whole) == a and "interrupted" not in a and "interrupted" not in a.get("meta", {})
    assert not (tmp_path / "out.json.ckpt.npz").exists() and _locks(tmp_path) == []
    if history:
        a, b = (tmp_path / "whole.npz").read_bytes(), (tmp_path / "out.npz").read_bytes()
        if not wall:                                   # one deterministic writer: the same bytes
            assert a == b
        with np.load(tmp_path / "whole.npz") as za, np.load(tmp_path / "out.npz") as zb:
            assert za.files == zb.files
            for k in za.files:
                if k not in wall:
                    np.testing.assert_array_equal(za[k], zb[k], err_msg=k)
