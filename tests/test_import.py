"""A good citizen: ``import jaxsleigh`` changes no JAX setting and does not start JAX, and no run replaces
anything inside JAX. Each check runs in a fresh Python process (JAX's settings and backends are per process)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _python(code: str, *args: str, **env) -> dict:
    """Run ``code`` (with ``args`` in ``sys.argv[1:]``) in a fresh process on CPU, with none of JAX's or jaxsleigh's
    settings in its environment; its last line of output, read as JSON."""
    full = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "JAXSLEIGH_", "XLA_"))}
    full.update(JAX_PLATFORMS="cpu", PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]), **env)
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], capture_output=True, text=True, env=full,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_importing_every_module_changes_no_jax_setting_and_starts_nothing():
    """Every module of the package (the command line's included) is imported; every one of ``jax.config``'s values
    is the same after as before, and JAX has not started: its CPU device count can still be chosen."""
    out = _python("""
        import importlib, json, pkgutil
        import jax

        def settings():
            return {k: repr(v) for k, v in jax.config.values.items()}

        before = settings()
        import jaxsleigh
        names = ["jaxsleigh"] + [m.name for m in pkgutil.walk_packages(jaxsleigh.__path__, "jaxsleigh.")
                                 if not m.name.endswith(".__main__")]
        for name in names:
            importlib.import_module(name)
        after = settings()
        changed = sorted(k for k in before if after.get(k) != before[k])
        jax.config.update("jax_num_cpu_devices", 3)     # refused (RuntimeError) once JAX has started
        print(json.dumps({"modules": names, "changed": changed, "devices": len(jax.devices())}))
    """)
    assert len(out["modules"]) > 50 and "jaxsleigh.cli" in out["modules"] and "jaxsleigh.cache" in out["modules"]
    assert out["changed"] == []
    assert out["devices"] == 3


def test_a_run_replaces_nothing_inside_jax(tmp_path):
    """Every function and class of every loaded module of JAX and jaxlib is the same object after a run as before it:
    a simulation with the compilation cache on, whose programs are kept exported and called through `jax.export`
    (where JAX initialises LAPACK), and a `solve`. The cache folder is the test suite's (`tests/conftest.py`), so
    that nothing is compiled afresh."""
    out = _python("""
        import json, sys, types
        from pathlib import Path
        import jax, jax.export, jax.numpy as jnp
        from jax._src.export import _export            # what an exported program's call lowers through
        from jax._src.lax import linalg                # where JAX initialises LAPACK for it
        import jaxsleigh as js

        KINDS = (types.FunctionType, types.BuiltinFunctionType, type)

        def objects():
            return {(m, a): id(v) for m, mod in list(sys.modules.items())
                    if m.split(".")[0] in ("jax", "jaxlib") and isinstance(mod, types.ModuleType)
                    for a, v in list(vars(mod).items()) if isinstance(v, KINDS)}

        before = objects()
        js.enable_compilation_cache(sys.argv[1])
        s = js.simulate([[1.0, 1.0, 0.5]], t_final=1.0, dt=0.01, saveat=js.SaveAt(every=10),
                        run=js.RunOptions(progress=False))
        js.solve(js.paper_gains(), jnp.asarray([1.0, 1.0, 0.5]), t_final=1.0).q_final.block_until_ready()
        after = objects()
        replaced = sorted(f"{m}.{a}" for (m, a), i in before.items() if (m, a) in after and after[m, a] != i)
        kept = list((Path(sys.argv[1]) / "exported").glob("*.stablehlo"))
        print(json.dumps({"replaced": replaced, "watched": len(before), "kept": len(kept),
                          "ensure": ("jax._src.export._export", "_ensure_backends_initialized") in before,
                          "status": s.status.tolist()}))
    """, os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(tmp_path / "cache"))   # the suite's cache, if it has one
    assert out["status"] == [0] and out["kept"] >= 3        # the exported programs ran
    assert out["ensure"] and out["watched"] > 1000
    assert out["replaced"] == []


def test_the_private_jax_name_jaxsleigh_reads_is_where_it_expects():
    """`jaxsleigh.jax_private` is the one module that reads a private JAX name (the cache's file suffixes): it fails
    here, not in a run, when JAX moves it; and no other module reaches into ``jax._src``."""
    import ast
    from pathlib import Path

    import jaxsleigh
    from jaxsleigh.jax_private import cache_entry_suffixes

    assert cache_entry_suffixes() == ("-cache", "-atime")
    root = Path(jaxsleigh.__file__).parent
    reach = [f"{p.relative_to(root)}:{n.lineno}" for p in root.rglob("*.py") if p.name != "jax_private.py"
             for n in ast.walk(ast.parse(p.read_text()))
             if isinstance(n, (ast.Import, ast.ImportFrom)) and "_src" in (
                 getattr(n, "module", None) or " ".join(a.name for a in n.names))]
    assert not reach, reach
