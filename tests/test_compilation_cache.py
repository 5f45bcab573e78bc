"""A Python program can use the command line's compilation cache (`jaxsleigh.enable_compilation_cache`)."""
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
        js.simulate([1.0, 1.0, 0.5], t_final=0.1, dt=0.01, save_every=1)
        print(d)
    """)
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXSLEIGH_CACHE_DIR": str(cache),
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    env.pop("JAXSLEIGH_NO_COMPILE_CACHE", None)
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert Path(r.stdout.strip()) == cache
    assert len([p for p in cache.rglob("*") if p.is_file()]) >= 1


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


@pytest.mark.parametrize("off", [False, True])
def test_import_alone_turns_the_cache_on_unless_told_not_to(tmp_path, off):
    """``import jaxsleigh`` is enough for a Python program to reuse (and fill) the command line's cache."""
    cache = tmp_path / "cache"
    code = "import jaxsleigh as js; js.simulate([1.0, 1.0, 0.5], t_final=0.1, dt=0.01, save_every=1)"
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXSLEIGH_CACHE_DIR": str(cache),
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    env.pop("JAXSLEIGH_NO_COMPILE_CACHE", None)
    if off:
        env["JAXSLEIGH_NO_COMPILE_CACHE"] = "1"
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    files = [p for p in cache.rglob("*") if p.is_file()] if cache.exists() else []
    assert (len(files) == 0) if off else (len(files) >= 3)
