"""JAX's persistent compilation cache for jaxsleigh: compile once per machine, not once per process.

The command line turns it on (``--no-compile-cache`` or ``JAXSLEIGH_NO_COMPILE_CACHE=1`` keeps it off); a Python
program turns it on with one call, `enable_compilation_cache` (``import jaxsleigh`` changes no JAX setting). Both
use the same folder (`compilation_cache_dir`), so a program compiled by one is reused by the other.

JAX's cache keeps compiled programs, but a new process must still trace and lower every function to find
its key: that was most of a second process after importing JAX. The engine's programs are therefore
`KeptProgram` objects: each traced program is also kept, exported as StableHLO (`jax.export`), in
``<cache folder>/exported`` under a key of everything it depends on, and a later process calls it without
tracing it (`KeptProgram` says what is in the key, and what is never kept). StableHLO is JAX's stable
exchange format; a file that cannot be read, parsed or lowered is exported again. Only the compiled
program itself comes from JAX's cache, as before.
"""
from __future__ import annotations

import functools
import hashlib
import inspect
import os
import pickle
import threading
import types
import warnings
from pathlib import Path
from typing import Optional, Union

import numpy as np

__all__ = ["compilation_cache_dir", "enable_compilation_cache"]

#: the persistent cache's bound in bytes (least recently used entries are evicted beyond it): a whole test
#: suite's programs take about 0.5 GB
CACHE_MAX_BYTES = 4 * 1024**3


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
    program or the command line) compiles nothing that was compiled before.

    The command line calls it when it starts; a Python program calls it once, before its first
    simulation (JAX reads the setting when it first compiles). It sets four of JAX's settings for
    the whole process: ``jax_compilation_cache_dir`` (the folder),
    ``jax_persistent_cache_min_compile_time_secs`` and ``jax_persistent_cache_min_entry_size_bytes``
    to 0 (every program is kept: the sleigh's are small and quick to compile, but many), and
    ``jax_compilation_cache_max_size`` to `CACHE_MAX_BYTES`. The bound is what makes the folder safe to
    share: without one, JAX writes entries in place and reads them without a lock, so a process that
    reads an entry another is still writing aborts (two test workers, or the processes of one basin,
    compiling the same program); with one, JAX takes a file lock around every read and write (the
    ``filelock`` package) and evicts the least recently used entries beyond the bound. With the
    cache on, the engine's traced programs are kept as well (`KeptProgram`, written atomically).

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
        # a bound turns on JAX's file lock around every read and write of the shared folder
        jax.config.update("jax_compilation_cache_max_size", CACHE_MAX_BYTES)
    _stamp_unbounded_entries(d)
    return d


def _stamp_unbounded_entries(d: Path) -> None:
    """Give every entry of ``d`` that an unbounded cache kept (an earlier jaxsleigh's, or JAX's own default) the
    access-time file a bounded cache keeps beside each entry, its file's modification time: without one, JAX's
    eviction fails on every write and keeps nothing new. Under JAX's lock; a no-op once done."""
    import filelock

    from .jax_private import cache_entry_suffixes

    entry, atime = cache_entry_suffixes()
    try:
        with filelock.FileLock(d / ".lockfile", timeout=10):
            for p in d.glob(f"*{entry}"):
                stamp = d / (p.name[: -len(entry)] + atime)
                if not stamp.exists():
                    stamp.write_bytes(p.stat().st_mtime_ns.to_bytes(8, "little"))
    except (OSError, filelock.Timeout):
        pass                      # another process holds the folder: it stamps them, or JAX warns and compiles


# --- programs kept exported: a second process skips tracing as well as compiling --------------------------------

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


def _source_digest() -> str:
    """A digest of jaxsleigh's own source and of the JAX that traces it: a kept program belongs to both."""
    if not _SOURCE_DIGEST:
        import jax
        import jaxlib

        h = hashlib.sha256(f"{jax.__version__} {jaxlib.__version__}".encode())
        root = Path(__file__).resolve().parent
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
        _SOURCE_DIGEST.append(h.hexdigest())
    return _SOURCE_DIGEST[0]


#: JAX's settings that change what a function traces to (they are in a kept program's key)
_TRACE_SETTINGS = ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion",
                   "jax_numpy_rank_promotion", "jax_enable_checks")


class KeptProgram:
    """A jitted function whose traced program is kept on disk (`jax.export`, StableHLO), so that a later
    process calls it without tracing it; JAX's persistent cache then finds the compiled program.

    It is called like the function under `jax.jit`, and gives the same bytes. A call is kept only where
    everything the program depends on is in its key: jaxsleigh's source and JAX's version, the function,
    its static arguments, the argument tree (node types and their static data, all of them jaxsleigh's,
    Python's or NumPy's: `_valuelike`) and every leaf's shape, dtype and weak type, the backend, and JAX's
    settings that change a trace (`_TRACE_SETTINGS`: float64 on or off, matmul precision, promotion rules).
    Anything else (a user's controller class, whose code is not in the key; a call under a
    transformation or `jax.disable_jit`; a multi-process run; the cache turned off; a file that cannot be
    read or written) runs through plain `jax.jit`, as before.
    """

    def __init__(self, fun, *, static_argnames=(), donate_argnums=()):
        import jax

        self.__wrapped__ = fun
        functools.update_wrapper(self, fun)
        self._sig = inspect.signature(fun)
        self._names = list(self._sig.parameters)
        self._static = tuple(static_argnames)
        self._donate = tuple(self._names[i] for i in donate_argnums)
        self._jit = jax.jit(fun, static_argnames=static_argnames, donate_argnums=donate_argnums)
        self._loaded: dict = {}                # key -> (jitted call, output tree, devices compiled for), or None
        self._first: dict = {}                 # (key, device) -> the lock of its first call
        self._keys: dict = {}                  # a call's signature -> its key (`_key_of`)
        self._lock = threading.Lock()

    def __call__(self, *args, **kwargs):
        folder = _kept_dir()
        if folder is None:
            return self._jit(*args, **kwargs)
        import jax

        bound = self._sig.bind(*args, **kwargs)
        bound.apply_defaults()
        static = {k: bound.arguments[k] for k in self._static}
        leaves, treedef = jax.tree_util.tree_flatten([bound.arguments[k] for k in self._names if k not in static])
        key = self._key_of(static, leaves, treedef)
        if key is not None and key not in self._loaded:
            with self._lock:
                if key not in self._loaded:
                    self._loaded[key] = self._load_or_export(folder, key, static, leaves, treedef)
        kept = None if key is None else self._loaded[key]
        if kept is None:
            return self._jit(*args, **kwargs)
        call, out_tree, ready = kept
        device = _device_of(leaves)
        leaves = _committed(leaves, device)
        if device in ready:
            return jax.tree_util.tree_unflatten(out_tree, call(*leaves))
        with self._lock:
            first = self._first.setdefault((key, device), threading.Lock())
        with first:                            # one compilation per program and device, not one per thread
            try:
                out = call(*leaves)
            except Exception:                  # a kept file that does not parse or lower
                self._loaded[key] = None
                (folder / f"{key}.stablehlo").unlink(missing_ok=True)
                return self._jit(*args, **kwargs)  # plain jit gives its own error, if there is one
            ready.add(device)
        return jax.tree_util.tree_unflatten(out_tree, out)

    def _cache_size(self) -> int:
        """How many programs this function has compiled or loaded in this process (as `jax.jit`'s)."""
        return self._jit._cache_size() + sum(c is not None for c in self._loaded.values())

    def _key_of(self, static: dict, leaves: list, treedef) -> Optional[str]:
        """`_key`, remembered for the call's signature (~0.3 us per leaf against ~0.1-1 ms for the key itself:
        the engine calls its programs once per segment and part, with the GIL held)."""
        import jax

        try:
            sig = (treedef, tuple(static.items()), tuple(map(_leaf_signature, leaves)), jax.default_backend(),
                   *(getattr(jax.config, k, None) for k in _TRACE_SETTINGS), jax.config.jax_disable_jit)
            hash(sig)
        except TypeError:                      # a leaf that is no array, or unhashable static data
            return self._key(static, leaves, treedef)
        if sig not in self._keys:
            self._keys[sig] = self._key(static, leaves, treedef)
        return self._keys[sig]

    def _key(self, static: dict, leaves: list, treedef) -> Optional[str]:
        """The program's key, or None where it cannot be kept."""
        import jax

        parts = [self.__wrapped__.__module__, self.__wrapped__.__qualname__, _source_digest(), jax.default_backend(),
                 *(f"{k}={getattr(jax.config, k, None)}" for k in _TRACE_SETTINGS)]
        if (not self.__wrapped__.__module__.startswith("jaxsleigh") or not hasattr(jax, "typeof")
                or jax.process_count() > 1 or jax.config.jax_disable_jit):
            return None            # code outside the digest; an older JAX; a multi-process run (JAX's own cache);
            #                        jit turned off (plain jit then runs op by op, as asked)
        for k, v in static.items():
            d = _describe_static(v)
            if d is None:
                return None
            parts.append(f"{k}={d}")
        if any(isinstance(x, jax.core.Tracer) for x in leaves) or not _describe_tree(treedef, parts):
            return None            # called under a transformation (it traces as plain jit), or not value-like
        for x in leaves:
            a = jax.typeof(x)
            parts.append(f"{a.dtype.name}{a.shape}{'~' if a.weak_type else ''}")
        return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:32]

    def _donated(self, static: dict, treedef) -> tuple:
        """The flat positions of the donated arguments' leaves."""
        names = [k for k in self._names if k not in static]
        counts = [c.num_leaves for c in treedef.children()]
        starts = np.cumsum([0] + counts[:-1])
        return tuple(i for k, c, s in zip(names, counts, starts) if k in self._donate for i in range(int(s), int(s) + c))

    def _load_or_export(self, folder: Path, key: str, static: dict, leaves: list, treedef):
        """``(jitted call, output tree)`` of the kept program: read from ``folder``, else exported (and written
        there); None where it cannot be exported (plain jit then runs it, or says what is wrong)."""
        import jax

        path = folder / f"{key}.stablehlo"
        kept = _read(path)
        if kept is None:
            kept = self._export(static, leaves, treedef)
            if kept is None:
                return None
            _write(path, *kept)
        exported, out_tree = kept
        call = jax.jit(exported.call, donate_argnums=self._donated(static, treedef))
        return call, out_tree, set()

    def _export(self, static: dict, leaves: list, treedef):
        """``(jax.export.Exported, output tree)`` of the function on flat arguments shaped as ``leaves``."""
        import jax
        from jax import export

        names = [k for k in self._names if k not in static]
        trees = []

        def flat(*xs):
            out_leaves, out_tree = jax.tree_util.tree_flatten(
                self.__wrapped__(**dict(zip(names, jax.tree_util.tree_unflatten(treedef, xs))), **static))
            trees.append(out_tree)
            return out_leaves

        specs = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type) for a in map(jax.typeof, leaves)]
        try:
            return export.export(jax.jit(flat))(*specs), trees[-1]
        except Exception:                      # plain jit says what went wrong, as before
            return None


def _read(path: Path):
    """``(Exported, output tree)`` from a kept file, or None where it is absent or damaged."""
    from jax import export

    try:
        blob = path.read_bytes()
        n = int.from_bytes(blob[:8], "little")
        return export.deserialize(bytearray(blob[8 + n:])), pickle.loads(blob[8:8 + n])
    except Exception:
        return None


def _write(path: Path, exported, out_tree) -> None:
    """Keep a program: the output tree (pickled), then the serialised export; atomically, where it can be
    written at all (else it is kept in this process only)."""
    try:
        head = pickle.dumps(out_tree)
        tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
        tmp.write_bytes(len(head).to_bytes(8, "little") + head + exported.serialize())
        os.replace(tmp, path)
    except Exception:
        pass


def _leaf_signature(x) -> tuple:
    """What of an argument decides its traced type: its class, shape, dtype and weak type (a Python number's is
    its class; x64 is in the signature beside it)."""
    return type(x), getattr(x, "shape", None), getattr(x, "dtype", None), getattr(x, "weak_type", None)


def _committed(leaves: list, device) -> list:
    """``leaves`` with every uncommitted JAX array committed to ``device``, as the exported program's own outputs
    are: a program fed both would compile twice per device. NumPy and Python leaves are left as they are (jit
    treats them alike every time), and so are committed arrays: in a segment loop this costs a few microseconds."""
    import jax

    idx = [i for i, x in enumerate(leaves) if isinstance(x, jax.Array) and not x.committed]
    if not idx:
        return leaves
    leaves = list(leaves)
    for i, x in zip(idx, jax.device_put([leaves[i] for i in idx], device)):
        leaves[i] = x
    return leaves


def _device_of(leaves):
    """The device a call runs on: that of its first committed array, else the default device (of this thread)."""
    import jax

    for x in leaves:
        if isinstance(x, jax.Array) and x.committed:
            return next(iter(x.devices()))
    default = jax.config.jax_default_device
    return default if isinstance(default, jax.Device) else jax.local_devices()[0]


def kept_jit(*, static_argnames=(), donate_argnums=()):
    """Decorator: `jax.jit` whose traced program is kept between processes (`KeptProgram`)."""
    return lambda fun: KeptProgram(fun, static_argnames=static_argnames, donate_argnums=donate_argnums)


_KEPT_DIRS: dict = {}


def _kept_dir() -> Optional[Path]:
    """``<compilation cache>/exported``, where the persistent cache is on (and the folder can be made); else None."""
    import jax

    d = jax.config.jax_compilation_cache_dir
    if not d or os.environ.get("JAXSLEIGH_NO_COMPILE_CACHE", "").strip() not in ("", "0"):
        return None
    if d not in _KEPT_DIRS:
        path = Path(d) / "exported"
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError:
            path = None
        _KEPT_DIRS[d] = path
    return _KEPT_DIRS[d]
