"""JAX's persistent compilation cache for jaxsleigh: compile once per machine, not once per process.

``import jaxsleigh`` turns it on (the command line and Python sessions alike; ``JAXSLEIGH_NO_COMPILE_CACHE=1``
keeps it off); `enable_compilation_cache` moves it to another folder. Both use the same folder
(`compilation_cache_dir`), so a program compiled by one is reused by the other.

JAX's cache keeps compiled programs, but a new process still traces and lowers every function to find its
key. The engine's programs are therefore `KeptProgram` objects: each compiled program is also kept (in
``<cache folder>/kept``) under a key of everything it depends on, and a later process loads it without
tracing (`KeptProgram` says what is in the key, and what is never kept).
"""
from __future__ import annotations

import functools
import os
import threading
import types
import warnings
from pathlib import Path
from typing import Optional, Union

import numpy as np

__all__ = ["compilation_cache_dir", "enable_compilation_cache"]


def compilation_cache_dir() -> Optional[Path]:
    """Where compiled programs are kept between processes: ``$JAXSLEIGH_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/jaxsleigh/jax`` (``~/.cache/jaxsleigh/jax``); ``None`` when turned off with
    ``JAXSLEIGH_NO_COMPILE_CACHE=1`` (or ``--no-compile-cache``)."""
    if os.environ.get("JAXSLEIGH_NO_COMPILE_CACHE", "").strip() not in ("", "0"):
        return None
    if os.environ.get("JAXSLEIGH_CACHE_DIR"):
        return Path(os.environ["JAXSLEIGH_CACHE_DIR"])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "jaxsleigh" / "jax"


def enable_compilation_cache(path: Union[str, os.PathLike, None] = None) -> Optional[Path]:
    """Turn on JAX's persistent compilation cache for this process: a later process (a Python
    session or the command line) compiles nothing that was compiled before.

    Call it once, before the first simulation (JAX reads the setting when it first compiles).

    Args:
      path: the cache folder. Default: the command line's (`compilation_cache_dir`:
        ``$JAXSLEIGH_CACHE_DIR``, else ``~/.cache/jaxsleigh/jax``), or none at all when
        ``JAXSLEIGH_NO_COMPILE_CACHE=1``; a default folder that cannot be created leaves the cache
        off (JAX then compiles as usual).

    Returns:
      The folder in use, or ``None`` when the cache stays off.

    Raises:
      ValueError: ``path`` was given but is empty, a file, or cannot be created.
    """
    if path is None:
        d = compilation_cache_dir()
        if d is None:
            return None
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError:
            return None
    else:
        if not isinstance(path, (str, os.PathLike)) or not str(path).strip():
            raise ValueError(f"path must be a folder for the compilation cache (or None for the default), "
                             f"got {path!r}")
        d = Path(path).expanduser()
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            what = "is a file" if d.is_file() else f"cannot be created ({e.strerror or e})"
            raise ValueError(f"path {str(d)!r} {what}; give a writable folder for the compilation cache, "
                             "or path=None for the default") from None
    import jax

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        jax.config.update("jax_compilation_cache_dir", str(d))
        # cache every program: the sleigh's are small and quick to compile, but many
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return d


# --- programs kept traced: a second process skips tracing and lowering as well as compiling ----------------------

#: what a kept program's key may name: the node and static types of jaxsleigh, and Python's and NumPy's
_OWN_MODULES = ("jaxsleigh", "builtins", "collections", "numpy")


def _own(typ) -> bool:
    return (getattr(typ, "__module__", None) or "").split(".")[0] in _OWN_MODULES


def _valuelike(obj, depth: int = 0) -> bool:
    """Whether ``obj`` is described by its repr alone: plain values and containers of them, and jaxsleigh's
    own objects and functions (their code is in the key) whose parts are such; never a user's class or
    function, wherever it sits."""
    if depth > 20:
        return False
    if obj is None or isinstance(obj, (bool, int, float, complex, str, bytes, np.dtype, np.generic)):
        return True
    if type(obj) in (tuple, list, frozenset, set):
        return all(_valuelike(v, depth + 1) for v in obj)
    if type(obj) is dict:
        return all(_valuelike(k, depth + 1) and _valuelike(v, depth + 1) for k, v in obj.items())
    if isinstance(obj, type):                                   # a class
        return _own(obj)
    if isinstance(obj, (types.FunctionType, types.BuiltinFunctionType, types.MethodType)):
        return (getattr(obj, "__module__", None) or "").split(".")[0] == "jaxsleigh"
    if not _own(type(obj)) or " at 0x" in repr(obj):           # a user's object, or one without a value repr
        return False
    parts = obj if hasattr(obj, "_fields") else getattr(obj, "__dict__", {}).values()
    return all(_valuelike(v, depth + 1) for v in parts)


def _describe_tree(treedef, out: list) -> bool:
    """Append the node types and their static data to ``out``; False where a node is not jaxsleigh's own
    (a user's class: its code is not in the key) or its static data is not value-like (`_valuelike`)."""
    nd = treedef.node_data()
    if nd is not None:
        typ, aux = nd
        if not _own(typ) or not _valuelike(aux):
            return False
        out.append(f"{typ.__module__}.{typ.__qualname__}:{aux!r}")
    return all(_describe_tree(c, out) for c in treedef.children())


def _describe_static(value) -> Optional[str]:
    """A value-like description of a static argument, or None where it holds code outside jaxsleigh."""
    if not _valuelike(value):
        return None
    return f"{type(value).__module__}.{type(value).__qualname__}:{value!r}"


_SOURCE_DIGEST: list = []


def _machine() -> str:
    """The CPU a kept program was compiled for: its architecture and, on Linux, its instruction-set flags."""
    import platform

    flags = ""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line for line in f if line.startswith(("flags", "Features"))), "")
    except OSError:
        pass
    return f"{platform.machine()} {flags.strip()}"


def _source_digest() -> str:
    """A digest of jaxsleigh's own source, of the JAX that traces it and of the CPU: a kept program belongs to all three."""
    if not _SOURCE_DIGEST:
        import hashlib

        import jax
        import jaxlib

        h = hashlib.sha256(f"{jax.__version__} {jaxlib.__version__} {_machine()}".encode())
        root = Path(__file__).resolve().parent
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
        _SOURCE_DIGEST.append(h.hexdigest())
    return _SOURCE_DIGEST[0]


class KeptProgram:
    """A jitted function whose compiled program is kept on disk with what it takes to call it
    (`jax.experimental.serialize_executable`), so that a later process runs it without tracing, lowering
    or looking it up in JAX's cache (which needs the lowered program for its key).

    It is called like the function under `jax.jit`. A call is kept only where everything the program
    depends on is in its key: jaxsleigh's source and JAX's version, the function, its static arguments,
    the argument tree (node types and their static data, all of them jaxsleigh's, Python's or NumPy's:
    `_valuelike`) and every leaf's shape, dtype and weak type, float64 on or off, the backend, the
    device and ``XLA_FLAGS``. Anything else (a user's controller class, whose code is not in the key;
    the cache turned off; a file that cannot be read or written) runs through plain `jax.jit`, as
    before. Like JAX's own cache, a kept program is machine code: keep the folder your own.
    """

    def __init__(self, fun, *, static_argnames=(), donate_argnums=()):
        import inspect

        import jax

        self.__wrapped__ = fun
        functools.update_wrapper(self, fun)
        self._sig = inspect.signature(fun)
        self._names = list(self._sig.parameters)
        self._static = tuple(static_argnames)
        self._donate = tuple(self._names[i] for i in donate_argnums)
        self._jit = jax.jit(fun, static_argnames=static_argnames, donate_argnums=donate_argnums)
        self._loaded: dict = {}

    def __call__(self, *args, **kwargs):
        folder = _kept_dir()
        if folder is None:
            return self._jit(*args, **kwargs)
        bound = self._sig.bind(*args, **kwargs)
        bound.apply_defaults()
        values = bound.arguments
        static = {k: values[k] for k in self._static}
        dynamic = [values[k] for k in self._names if k not in static]
        key, device = self._key(static, dynamic)
        compiled = None
        if key is not None:
            compiled = self._loaded[key] if key in self._loaded else self._load_or_compile(folder, key, device, static, dynamic)
        if compiled is None:
            return self._jit(*args, **kwargs)
        import jax

        return compiled(*jax.tree_util.tree_leaves(dynamic))

    def _cache_size(self) -> int:
        """How many programs this function has compiled or loaded in this process (as `jax.jit`'s)."""
        return self._jit._cache_size() + sum(c is not None for c in self._loaded.values())

    def _own_source(self) -> Optional[str]:
        """The digest of the function's own file where it is not jaxsleigh's (its code is then in the key too)."""
        if not hasattr(self, "_file_digest"):
            import hashlib
            import inspect

            fun = self.__wrapped__
            try:
                mine = (fun.__module__ or "").split(".")[0] == "jaxsleigh"
                self._file_digest = "" if mine else hashlib.sha256(Path(inspect.getsourcefile(fun)).read_bytes()).hexdigest()
            except (OSError, TypeError):
                self._file_digest = None
        return self._file_digest

    def _key(self, static: dict, dynamic: list) -> tuple:
        """``(key, device)``: the program's key (None where it cannot be kept) and the device it runs on."""
        import hashlib

        import jax

        parts = [self.__wrapped__.__module__, self.__wrapped__.__qualname__, _source_digest(), self._own_source(),
                 f"x64={jax.config.jax_enable_x64}", jax.default_backend(), os.environ.get("XLA_FLAGS", "")]
        if parts[3] is None or not hasattr(jax, "typeof") or jax.process_count() > 1:
            return None, None      # no source to put in the key; an older JAX; a multi-process run (JAX's own cache)
        for k, v in static.items():
            d = _describe_static(v)
            if d is None:
                return None, None
            parts.append(f"{k}={d}")
        leaves, treedef = jax.tree_util.tree_flatten(dynamic)
        if any(isinstance(x, jax.core.Tracer) for x in leaves) or not _describe_tree(treedef, parts):
            return None, None      # called under a transformation (it traces as plain jit), or not value-like
        device = None
        for x in leaves:
            a = jax.typeof(x)
            parts.append(f"{a.dtype.name}{a.shape}{'~' if a.weak_type else ''}")
            if isinstance(x, jax.Array) and device is None and getattr(x, "committed", False):
                device = next(iter(x.devices()))
        if device is None:
            default = jax.config.jax_default_device
            device = default if isinstance(default, jax.Device) else jax.local_devices()[0]
        parts.append(str(device))
        return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:32], device

    def _load_or_compile(self, folder: Path, key: str, device, static: dict, dynamic: list):
        import pickle

        import jax
        from jax.experimental import serialize_executable

        path = folder / f"{key}.exe"
        try:
            blob = path.read_bytes()
            n = int.from_bytes(blob[:8], "little")
            compiled = serialize_executable.deserialize_and_load(blob[8 + n:], *pickle.loads(blob[8:8 + n]),
                                                                execution_devices=[device])
        except Exception:                      # absent, or damaged: compile it (again)
            compiled = None
        if compiled is None:
            leaves, in_tree = jax.tree_util.tree_flatten(dynamic)
            names = [k for k in self._names if k not in static]
            counts = [len(jax.tree_util.tree_leaves(v)) for v in dynamic]
            donate = tuple(i for k, c, start in zip(names, counts, np.cumsum([0] + counts[:-1]))
                           if k in self._donate for i in range(int(start), int(start) + c))

            def flat(*xs):
                return self.__wrapped__(**dict(zip(names, jax.tree_util.tree_unflatten(in_tree, xs))), **static)

            try:
                # compiled afresh, not taken from JAX's cache: an executable loaded from there serialises
                # without its machine code on CPU ("Function ... not found" when the copy runs)
                with _jax_cache_off():
                    compiled = jax.jit(flat, donate_argnums=donate).lower(*leaves).compile()
            except Exception:                  # plain jit says what went wrong, as before
                self._loaded[key] = None
                return None
            try:
                payload, in_t, out_t = serialize_executable.serialize(compiled)
                head = pickle.dumps((in_t, out_t))
                tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
                tmp.write_bytes(len(head).to_bytes(8, "little") + head + payload)
                os.replace(tmp, path)
            except Exception:                  # not serialisable or not writable here: kept in memory only
                pass
        self._loaded[key] = compiled
        return compiled


def _jax_cache_off():
    """A context (this thread) in which JAX neither reads nor writes its persistent cache.

    JAX decides once per process, at its first compilation, whether its cache is used at all; that
    decision is made here first, outside the context, so that the rest of the process keeps the cache."""
    import jax
    from jax._src import compilation_cache, config

    compilation_cache.is_cache_used(jax.local_devices()[0].client)
    return config.enable_compilation_cache(False)


def kept_jit(*, static_argnames=(), donate_argnums=()):
    """Decorator: `jax.jit` whose compiled program is kept between processes (`KeptProgram`)."""
    return lambda fun: KeptProgram(fun, static_argnames=static_argnames, donate_argnums=donate_argnums)


_KEPT_DIRS: dict = {}


def _kept_dir() -> Optional[Path]:
    """``<compilation cache>/kept``, where the persistent cache is on (and the folder can be made); else None."""
    import jax

    d = jax.config.jax_compilation_cache_dir
    if not d or os.environ.get("JAXSLEIGH_NO_COMPILE_CACHE", "").strip() not in ("", "0"):
        return None
    if d not in _KEPT_DIRS:
        path = Path(d) / "kept"
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError:
            path = None
        _KEPT_DIRS[d] = path
    return _KEPT_DIRS[d]
