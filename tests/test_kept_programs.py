"""Programs kept traced between processes (`jaxsleigh.cache.KeptProgram`): a later process loads them
instead of tracing, gets the same bytes, and never loads a program whose code is not in its key."""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh import cache
from jaxsleigh.integrate import engine
from jaxsleigh.studies import simulate as simulate_module

PROGRAMS = [engine._w_check, engine._to_w_batch, engine._init_batch, engine._active, engine._segment_batch,
            engine._saving_batch, simulate_module._outputs]
ICS = np.array([[-3.0, -2.0, np.pi / 8], [1.0, 1.0, 0.5]])


def _new_process():
    """Forget every program loaded in this process, as a fresh process would."""
    for p in PROGRAMS:
        p._loaded.clear()


@pytest.fixture
def kept(monkeypatch, tmp_path):
    folder = tmp_path / "kept"
    folder.mkdir()
    monkeypatch.setattr(cache, "_kept_dir", lambda: folder)
    _new_process()
    yield folder
    _new_process()


def _run(**kw):
    sol = js.simulate(ICS, t_final=2.0, dt=0.01, save_every=10, progress=False, **kw)
    return np.concatenate([sol.q.ravel(), sol.p.ravel(), sol.u.ravel(), sol.n_steps.ravel().astype(float)])


def _plain(monkeypatch, **kw):
    with monkeypatch.context() as m:
        m.setattr(cache, "_kept_dir", lambda: None)
        return _run(**kw)


@pytest.mark.parametrize("x64", [False, True])
def test_a_later_process_loads_instead_of_tracing_and_gets_the_same_bytes(kept, monkeypatch, x64):
    first = _run(x64=x64)
    files = sorted(kept.glob("*.exe"))
    assert len(files) == 4          # chart change, first state, the saving loop, the outputs
    _new_process()

    def no_tracing(*a, **k):
        raise AssertionError("a kept program was traced again")

    monkeypatch.setattr(jax, "jit", no_tracing)
    second = _run(x64=x64)
    assert sorted(kept.glob("*.exe")) == files
    assert first.tobytes() == second.tobytes()
    assert first.tobytes() == _plain(monkeypatch, x64=x64).tobytes()


class PD(NamedTuple):
    """A user's law: its code lives outside jaxsleigh, so no program that holds it may be kept."""
    kp: float = 2.0

    def __call__(self, q, v):
        return -self.kp * jnp.stack([q[0] * jnp.cos(q[2]) + q[1] * jnp.sin(q[2]) + v[0], q[2] + v[1]])


def test_a_users_class_is_never_kept(kept, monkeypatch):
    out = _run(controller=PD())
    assert list(kept.iterdir()) == []
    assert out.tobytes() == _plain(monkeypatch, controller=PD()).tobytes()


def test_a_damaged_file_is_compiled_again(kept, monkeypatch):
    first = _run()
    for f in kept.glob("*.exe"):
        f.write_bytes(b"\x05\x00\x00\x00\x00\x00\x00\x00garbage")
    _new_process()
    assert _run().tobytes() == first.tobytes()
    assert all(f.stat().st_size > 1000 for f in kept.glob("*.exe"))


def test_the_key_names_shape_dtype_and_static_arguments():
    key = lambda *a: engine._to_w_batch._key(*a)[0]  # noqa: E731
    k = key({}, [np.ones((2, 5), np.float32)])
    assert k == key({}, [np.ones((2, 5), np.float32)])
    assert k != key({}, [np.ones((3, 5), np.float32)])
    assert k != key({}, [np.ones((2, 5), np.int32)])
    with jax.enable_x64(True):
        assert k != key({}, [np.ones((2, 5), np.float32)])
    obs = js.observers.DEFAULT_OBSERVERS
    assert cache._describe_static(obs) != cache._describe_static(obs[:2])
    assert cache._describe_static(lambda x: x) is None
    assert cache._describe_static((1, PD())) is None


def test_the_rest_of_the_process_keeps_jaxs_cache(tmp_path):
    """A kept program compiles outside JAX's cache; JAX decides once per process whether its cache is on,
    so a kept program compiled first must not turn it off for the programs compiled after it."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    cache_dir = tmp_path / "cache"
    code = ("import jax, jaxsleigh as js; js.simulate([1.0, 1.0, 0.5], t_final=0.1, dt=0.01, save_every=1); "
            "jax.jit(lambda x: x * 3.25 + 1.0)(2.0)")
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXSLEIGH_CACHE_DIR": str(cache_dir),
           "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    env.pop("JAXSLEIGH_NO_COMPILE_CACHE", None)
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300,
                       cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert len(list((cache_dir / "kept").glob("*.exe"))) >= 3
    assert any(p.name.startswith("jit__lambda") for p in cache_dir.iterdir()), sorted(p.name for p in cache_dir.iterdir())
