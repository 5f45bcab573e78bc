"""A Python program can use the command line's compilation cache with one call (`jaxsleigh.enable_compilation_cache`);
``import jaxsleigh`` alone leaves it off, and the command line turns it on unless told not to."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import jaxsleigh
from jaxsleigh.cache import compilation_cache_dir, enable_compilation_cache

ROOT = Path(__file__).resolve().parents[1]


def _env(cache: Path, **extra) -> dict:
    """A fresh process's environment: CPU, ``JAXSLEIGH_CACHE_DIR=cache``, and no cache setting of JAX's or
    jaxsleigh's inherited (the test suite's own, `tests/conftest.py`, included)."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE", "JAXSLEIGH_"))}
    env.update(JAX_PLATFORMS="cpu", JAXSLEIGH_CACHE_DIR=str(cache),
               PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]), **extra)
    return env


def test_python_program_fills_the_same_folder_as_the_command_line(tmp_path):
    """With no argument, the folder is the command line's (``$JAXSLEIGH_CACHE_DIR`` here); a
    simulation then writes compiled programs there. In a fresh process: the setting is global."""
    cache = tmp_path / "cache"
    code = textwrap.dedent("""
        import sys
        import jaxsleigh as js
        from jaxsleigh.cli.common import compilation_cache_dir
        d = js.enable_compilation_cache()
        assert d == compilation_cache_dir(), (d, compilation_cache_dir())
        js.simulate([1.0, 1.0, 0.5], t_final=0.1, dt=0.01, saveat=js.SaveAt(every=1))
        import jax
        assert jax.config.jax_compilation_cache_max_size == js.cache.CACHE_MAX_BYTES > 0
        print(d)
    """)
    r = subprocess.run([sys.executable, "-c", code], env=_env(cache), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert Path(r.stdout.strip()) == cache
    assert len([p for p in cache.rglob("*") if p.is_file()]) >= 1
    # the folder is shared between processes: JAX read and wrote it under its file lock (a bounded cache's),
    # so no process reads an entry another is still writing
    assert (cache / ".lockfile").exists()


def test_entries_an_unbounded_cache_kept_are_stamped_so_that_the_bounded_one_keeps_writing(tmp_path):
    """A folder filled by an unbounded cache (an earlier jaxsleigh's) has entries without access-time files; JAX's
    bounded cache reads one for every entry before it writes. `enable_compilation_cache` stamps them (their
    modification time) and leaves stamped ones alone."""
    d = tmp_path / "old"
    d.mkdir()
    (d / "jit_f-abc-cache").write_bytes(b"x" * 10)
    (d / "jit_g-def-cache").write_bytes(b"y")
    (d / "jit_g-def-atime").write_bytes((7).to_bytes(8, "little"))
    jaxsleigh.cache._stamp_unbounded_entries(d)
    assert int.from_bytes((d / "jit_f-abc-atime").read_bytes(), "little") == (d / "jit_f-abc-cache").stat().st_mtime_ns
    assert int.from_bytes((d / "jit_g-def-atime").read_bytes(), "little") == 7


def test_default_folder_and_off_switch(monkeypatch, tmp_path):
    monkeypatch.delenv("JAXSLEIGH_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("JAXSLEIGH_NO_COMPILE_CACHE", raising=False)
    assert compilation_cache_dir() == tmp_path / "jaxsleigh" / "jax"
    monkeypatch.setenv("JAXSLEIGH_NO_COMPILE_CACHE", "1")
    assert compilation_cache_dir() is None and enable_compilation_cache() is None
    assert jaxsleigh.enable_compilation_cache is enable_compilation_cache


@pytest.mark.parametrize("bad", ["", "   ", 3, "FILE"])
def test_bad_path_is_a_value_error_naming_path(tmp_path, bad):
    """A path that cannot be a folder is refused before JAX's settings are touched."""
    if bad == "FILE":
        bad = tmp_path / "a_file"
        bad.write_text("x")
    with pytest.raises(ValueError, match=r"^path .*(folder|file)"):
        enable_compilation_cache(bad)


def test_import_alone_leaves_the_cache_off(tmp_path):
    """``import jaxsleigh`` turns nothing on: a program that does not call `jaxsleigh.enable_compilation_cache`
    writes no compiled program and leaves JAX's cache setting unset (the call itself: the tests above)."""
    cache = tmp_path / "cache"
    code = textwrap.dedent("""
        import jax, jaxsleigh as js
        js.simulate([1.0, 1.0, 0.5], t_final=0.1, dt=0.01, saveat=js.SaveAt(every=1))
        print(jax.config.jax_compilation_cache_dir)
    """)
    r = subprocess.run([sys.executable, "-c", code], env=_env(cache), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert not cache.exists() or not [p for p in cache.rglob("*") if p.is_file()]
    assert r.stdout.strip().splitlines()[-1] == "None"


def test_the_command_lines_no_compile_cache_keeps_it_off(tmp_path):
    """``--no-compile-cache`` leaves the cache folder empty (it did nothing while the import turned the cache on);
    the command line's own cache and ``JAXSLEIGH_NO_COMPILE_CACHE=1``: tests/test_reliability.py."""
    cache = tmp_path / "cache"
    r = subprocess.run([sys.executable, "-m", "jaxsleigh.cli", "--no-compile-cache", "simulate", "--ic", "1,1,0.5",
                        "--t-final", "0.1", "--out", str(tmp_path / "r.npz")], env=_env(cache), capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert not cache.exists() or not [p for p in cache.rglob("*") if p.is_file()]
