"""Programs kept traced between processes (`jaxsleigh.cache.KeptProgram`, `jax.export`): a later process
loads them instead of tracing, gets the same bytes as plain `jax.jit`, and never loads a program whose code
is not in its key."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh import cache
from jaxsleigh.integrate import engine
from jaxsleigh.studies import ensemble
from jaxsleigh.studies import simulate as simulate_module

PROGRAMS = [engine._w_check, engine._to_w_batch, engine._init_batch, engine._segment_batch,
            engine._saving_batch, simulate_module._outputs, ensemble._hd_batch, ensemble._hd_lanes,
            ensemble._to_q_batch]
ICS = np.array([[-3.0, -2.0, np.pi / 8], [1.0, 1.0, 0.5]])


def _new_process():
    """Forget every program loaded in this process, as a fresh process would."""
    for p in PROGRAMS:
        p._loaded.clear()


@pytest.fixture
def kept(monkeypatch, tmp_path):
    folder = tmp_path / "exported"
    folder.mkdir()
    monkeypatch.setattr(cache, "_kept_dir", lambda: folder)
    _new_process()
    yield folder
    _new_process()


def _run(**kw):
    sol = js.simulate(ICS, t_final=2.0, dt=0.01, saveat=js.SaveAt(every=10), run=js.RunOptions(progress=False), **kw)
    return np.concatenate([sol.q.ravel(), sol.p.ravel(), sol.u.ravel(), sol.n_steps.ravel().astype(float)])


def _plain(monkeypatch, **kw):
    with monkeypatch.context() as m:
        m.setattr(cache, "_kept_dir", lambda: None)
        return _run(**kw)


@pytest.mark.parametrize("x64", [False, True])
def test_a_later_process_loads_instead_of_tracing_and_gets_the_same_bytes(kept, monkeypatch, x64):
    first = _run(x64=x64)
    files = sorted(kept.glob("*.stablehlo"))
    assert len(files) == 4          # chart change, first state, the saving loop, the outputs
    _new_process()

    def no_tracing(*a, **k):
        raise AssertionError("a kept program was traced again")

    compiled = {id(p): p._jit._cache_size() for p in PROGRAMS}
    monkeypatch.setattr(cache.KeptProgram, "_export", no_tracing)
    second = _run(x64=x64)
    assert sorted(kept.glob("*.stablehlo")) == files
    assert all(p._jit._cache_size() == compiled[id(p)] for p in PROGRAMS)   # nothing went through plain jit
    assert first.tobytes() == second.tobytes()
    monkeypatch.undo()
    assert first.tobytes() == _plain(monkeypatch, x64=x64).tobytes()


def test_an_ensemble_is_the_same_bytes_kept_or_not(kept, monkeypatch):
    starts = js.sample_starts(64, seed=3).ics
    kw = dict(t_final=5.0, run=js.RunOptions(progress=False))
    a = js.run_ensemble(starts, **kw)
    assert len(list(kept.glob("*.stablehlo"))) >= 3
    with monkeypatch.context() as m:
        m.setattr(cache, "_kept_dir", lambda: None)
        b = js.run_ensemble(starts, **kw)
    for name in ("q_final", "p_final", "T_eps", "Hd0", "Hd_final", "u_energy", "n_steps", "status"):
        assert np.asarray(getattr(a, name)).tobytes() == np.asarray(getattr(b, name)).tobytes(), name


class PD(NamedTuple):
    """A user's law: its code lives outside jaxsleigh, so no program that holds it may be kept."""
    kp: float = 2.0

    def __call__(self, q, v):
        return -self.kp * jnp.stack([q[0] * jnp.cos(q[2]) + q[1] * jnp.sin(q[2]) + v[0], q[2] + v[1]])


def test_a_users_class_is_never_kept(kept, monkeypatch):
    out = _run(controller=PD())
    assert list(kept.iterdir()) == []
    assert out.tobytes() == _plain(monkeypatch, controller=PD()).tobytes()


def test_a_damaged_file_is_exported_again(kept):
    first = _run()
    for f in kept.glob("*.stablehlo"):
        f.write_bytes(b"\x05\x00\x00\x00\x00\x00\x00\x00garbage")
    _new_process()
    assert _run().tobytes() == first.tobytes()
    assert all(f.stat().st_size > 1000 for f in kept.glob("*.stablehlo"))


def test_the_key_names_shape_dtype_and_static_arguments():
    def key(static, args):
        leaves, tree = jax.tree_util.tree_flatten(args)
        return engine._to_w_batch._key(static, leaves, tree)

    k = key({}, [np.ones((2, 5), np.float32)])
    assert k is not None and k == key({}, [np.ones((2, 5), np.float32)])
    assert k != key({}, [np.ones((3, 5), np.float32)])
    assert k != key({}, [np.ones((2, 5), np.int32)])
    with jax.enable_x64(True):
        assert k != key({}, [np.ones((2, 5), np.float32)])
    with jax.default_matmul_precision("highest"):
        assert k != key({}, [np.ones((2, 5), np.float32)])
    with jax.disable_jit():
        assert key({}, [np.ones((2, 5), np.float32)]) is None      # op by op, as asked
    # the remembered key of a call's signature is the key itself, settings and dtypes included
    for args in ([np.ones((2, 5), np.float64)], [jnp.ones((2, 5))], [1.0], [np.float32(1.0)], [1]):
        leaves, tree = jax.tree_util.tree_flatten(args)
        for x64 in (False, True):
            with jax.enable_x64(x64):
                assert engine._to_w_batch._key_of({}, leaves, tree) == engine._to_w_batch._key({}, leaves, tree)
    assert key({}, [PD()]) is None                        # a user's node type in the arguments
    obs = js.observers.DEFAULT_OBSERVERS
    assert cache._describe_static(obs) != cache._describe_static(obs[:2])
    assert cache._describe_static(lambda x: x) is None
    assert cache._describe_static((1, PD())) is None


def test_a_second_process_traces_nothing(tmp_path):
    """Two real processes share a cache folder (each turns it on with `jaxsleigh.enable_compilation_cache`): the
    second traces no program (it loads each from its file), writes none and gives the same bytes."""
    code = ("import sys, numpy as np, jaxsleigh as js\n"
            "from jaxsleigh.cache import KeptProgram\n"
            "traced, export = [], KeptProgram._export\n"
            "KeptProgram._export = lambda self, *a: traced.append(1) or export(self, *a)\n"
            "js.enable_compilation_cache()\n"
            "s = js.simulate([[1.0, 1.0, 0.5]], t_final=1.0, dt=0.01, saveat=js.SaveAt(every=10),\n"
            "                run=js.RunOptions(progress=False))\n"
            "np.save(sys.argv[1], np.concatenate([s.q.ravel(), s.u.ravel()]))\n"
            "print(len(traced))\n")
    root = Path(__file__).resolve().parents[1]
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE", "JAXSLEIGH_"))}
    env.update(JAX_PLATFORMS="cpu", JAXSLEIGH_CACHE_DIR=str(tmp_path / "cache"),
               PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]))
    outs, listings = [], []
    for i in range(2):
        r = subprocess.run([sys.executable, "-c", code, str(tmp_path / f"run{i}.npy")], env=env,
                           capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        outs.append(r.stdout.strip().splitlines()[-1])
        listings.append(sorted(p.name for p in (tmp_path / "cache").rglob("*") if p.is_file()))
    assert len([n for n in listings[0] if n.endswith(".stablehlo")]) >= 3
    assert listings[1] == listings[0]
    assert np.load(tmp_path / "run0.npy").tobytes() == np.load(tmp_path / "run1.npy").tobytes()
    assert int(outs[0]) >= 3 and outs[1] == "0"         # the first process traced the programs, the second none


def test_a_file_that_reads_but_does_not_lower_is_exported_again(kept):
    """A kept file whose StableHLO is damaged reads (its frame is whole) but fails at its first call: the call
    goes through plain jit, the file is dropped, and the next process exports it afresh."""
    import dataclasses

    from jax import export

    first = _run()
    files = sorted(kept.glob("*.stablehlo"))
    for f in files:
        blob = f.read_bytes()
        n = int.from_bytes(blob[:8], "little")
        bad = dataclasses.replace(export.deserialize(bytearray(blob[8 + n:])), mlir_module_serialized=b"garbage")
        f.write_bytes(blob[:8 + n] + bad.serialize())
    _new_process()
    assert _run().tobytes() == first.tobytes()
    assert list(kept.glob("*.stablehlo")) == []           # each dropped at its failed first call
    _new_process()
    assert _run().tobytes() == first.tobytes()
    assert sorted(kept.glob("*.stablehlo")) == files
