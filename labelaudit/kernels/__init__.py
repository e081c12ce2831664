"""The package's compiled loops (:func:`kernel`), run ahead-of-time compiled or by numba's JIT.

Every compiled loop of labelaudit is a plain Python function decorated with :func:`kernel`. It runs
one of two ways, with the same results bit for bit (a test compares them):

- **ahead of time**: ``python -m labelaudit.kernels build`` (run by ``scripts/dev.sh``; the program is
  :mod:`labelaudit.kernels.__main__`) compiles every kernel, at the argument types the pipeline passes,
  into one extension module in the package directory
  (numba's ``pycc``; it needs a C compiler). A process then loads all of them in about a millisecond,
  without importing numba or LLVM: that is most of a worker's start-up otherwise (numba's set-up,
  a ``scipy.linalg`` import it always makes, and loading ~30 cached kernels: about 1 s).
- **just in time**: ``numba.njit(cache=True)``, compiled on first use and cached on disk. This is the
  path when the module was not built, was built from other sources (any change to a file holding
  kernels), for another interpreter, NumPy or CPU, or when ``LABELAUDIT_KERNELS=jit``. A call whose
  argument types the build did not see also takes it, for that kernel alone.

The ahead-of-time module is compiled for this machine's CPU (as numba's JIT is), so it is not
copied to other machines: its fingerprint names the CPU, and elsewhere the JIT path is taken.

``python -m labelaudit.kernels`` prints which path a process takes and why.

Every core module imports this one, so it imports nothing of the package (NumPy only; numba on the
JIT path and in the build): what the build runs to see the argument types spans the whole package
and is the program's (:mod:`labelaudit.kernels.__main__`), handed to :func:`build`.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import platform
import sys
import sysconfig
import tempfile
import types as pytypes
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["kernel", "kernel_mode", "build"]

MODE_ENV = "LABELAUDIT_KERNELS"  # "jit": never load the ahead-of-time module; "aot": fail loudly when it cannot be used
AOT_NAME = "_kernels_aot"  # the extension module's name (a sibling of this file)
_PACKAGE_DIR = Path(__file__).resolve().parents[1]  # labelaudit/
_SELF = str(
    Path(__file__).resolve().relative_to(_PACKAGE_DIR)
)  # this module's source: it shapes every compiled function
_TABLE = _PACKAGE_DIR / f"{AOT_NAME}.json"  # what the module holds: fingerprint, kernel → exported functions

_REGISTRY: dict[
    str, Kernel | Any
] = {}  # "module.qualname" → the decorated kernel (Kernel, or a numba dispatcher on the JIT path)
_STATE: dict[str, Any] = {}  # the chosen path, loaded once per process: mode, reason, module, table


# --- which path ------------------------------------------------------------------------------------


def _cpu_identity() -> str:
    """The CPU the ahead-of-time code may use (model and instruction-set flags; Linux)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            lines = [line for line in (f.readline() for _ in range(64)) if line.startswith(("model name", "flags"))]
    except OSError:
        lines = []
    return platform.machine() + "|" + "|".join(sorted(set(lines)))


def fingerprint(sources: list[str]) -> str:
    """What an ahead-of-time module must have been built from: the kernel sources (paths relative to
    the package), the interpreter's extension ABI, NumPy's version and the CPU."""
    h = hashlib.sha256()
    for rel in sorted(sources):
        h.update(rel.encode())
        try:
            h.update((_PACKAGE_DIR / rel).read_bytes())
        except OSError:
            h.update(b"<missing>")
    h.update(str(sysconfig.get_config_var("EXT_SUFFIX")).encode())
    h.update(np.__version__.encode())
    h.update(_cpu_identity().encode())
    return h.hexdigest()


def _choose() -> dict[str, Any]:
    if _STATE:
        return _STATE
    want = os.environ.get(MODE_ENV, "").strip().lower()
    state: dict[str, Any] = {"mode": "jit", "module": None, "table": {}}
    if want == "jit":
        state["reason"] = f"{MODE_ENV}=jit"
    else:
        try:
            table = json.loads(_TABLE.read_text(encoding="utf-8"))
            if table.get("fingerprint") != fingerprint(table.get("sources", [])):
                state["reason"] = (
                    f"{_TABLE.name} was built from other sources, NumPy or CPU (run: python -m labelaudit.kernels build)"
                )
            else:
                module = importlib.import_module(f"labelaudit.{AOT_NAME}")
                if not hasattr(module, f"build_{table['token']}"):  # the table and the module of two builds
                    raise ImportError(
                        f"{_TABLE.name} does not describe the module beside it (rebuild: python -m labelaudit.kernels build)"
                    )
                state.update(
                    mode="aot", module=module, table=table["kernels"], reason=f"built {table.get('built', '?')}"
                )
        except FileNotFoundError:
            state["reason"] = "not built (run: python -m labelaudit.kernels build)"
        except (OSError, ValueError, KeyError, ImportError) as exc:
            state["reason"] = f"cannot load the ahead-of-time module: {exc}"
        if want == "aot" and state["mode"] != "aot":
            raise ImportError(f"{MODE_ENV}=aot, but {state['reason']}")
    _STATE.update(state)
    return _STATE


def kernel_mode() -> tuple[str, str]:
    """``("aot" | "jit", why)`` for this process."""
    s = _choose()
    return s["mode"], s["reason"]


# --- the decorator ---------------------------------------------------------------------------------


def kernel(fn: Callable[..., Any] | None = None, **options: Any) -> Any:
    """Compile ``fn`` (a numba nopython function); ``options`` are numba's (``fastmath``,
    ``error_model``, ``inline``). Use as ``@kernel`` or ``@kernel(error_model="numpy")``.

    On the JIT path it returns ``numba.njit(cache=True, **options)(fn)``; on the ahead-of-time path a
    function that calls the compiled function matching its arguments' types (:class:`Kernel`).
    """
    if fn is None:
        return lambda f: kernel(f, **options)
    name = f"{fn.__module__}.{fn.__qualname__}"
    state = _choose()
    if state["mode"] == "aot":
        k: Any = Kernel(fn, options, state["module"], state["table"].get(name, []))
        _REGISTRY[name] = k
        return k.dispatch
    import numba  # only on this path

    _REGISTRY[name] = numba.njit(cache=True, **options)(fn)
    return _REGISTRY[name]


_SCALAR_KEYS: dict[type, str] = {
    float: "float64",
    int: "int64",
    bool: "bool",
    np.float64: "float64",
    np.float32: "float32",
    np.int64: "int64",
    np.int32: "int32",
    np.bool_: "bool",
    np.uint8: "uint8",
    np.intp: "int64",
}


def _arg_key(a: Any) -> Any:
    """The key of one argument's numba type (what numba's dispatcher would type it as); None when
    it is not one the ahead-of-time module can take."""
    t = type(a)
    if t is np.ndarray:
        f = a.flags
        return (
            "A",
            a.dtype.str,
            a.ndim,
            "C" if f.c_contiguous else ("F" if f.f_contiguous else "A"),
            f.writeable,
            f.aligned,
        )
    key = _SCALAR_KEYS.get(t)
    if key is not None:
        return key
    if t is tuple:
        return ("T", *(_arg_key(x) for x in a))
    return None


def _freeze(key: Any) -> Any:
    """A JSON list key back to the tuple :func:`_arg_key` makes."""
    return tuple(_freeze(x) for x in key) if isinstance(key, list) else key


def _test_of(i: int, key: Any, env: dict[str, Any], tag: str) -> str | None:
    """A Python expression true when argument ``a{i}`` has the numba type of ``key`` (None: no
    quick test for it, the keyed lookup decides); the names it puts in ``env`` end in ``tag``
    (one per signature)."""
    v, d, f, s = f"a{i}", f"_d{i}_{tag}", f"_f{i}", f"_s{i}_{tag}"
    if isinstance(key, tuple) and key[0] == "A":
        _, dtype, ndim, layout, mutable, aligned = key
        env[d] = np.dtype(dtype)
        flags = f"({f} := {v}.flags)"
        contiguity = {
            "C": f"{flags}.c_contiguous",
            "F": f"not {flags}.c_contiguous and {f}.f_contiguous",
            "A": f"not {flags}.c_contiguous and not {f}.f_contiguous",
        }[layout]
        return (
            f"type({v}) is _ndarray and ({v}.dtype is {d} or {v}.dtype == {d}) and {v}.ndim == {ndim} and {contiguity}"
            f" and {'' if mutable else 'not '}{f}.writeable and {'' if aligned else 'not '}{f}.aligned"
        )
    if isinstance(key, str):
        env[s] = frozenset(t for t, k in _SCALAR_KEYS.items() if k == key)
        return f"type({v}) in {s}"
    if isinstance(key, tuple) and key[0] == "T" and all(isinstance(k, str) for k in key[1:]):  # a tuple of scalars
        items = []
        for j, k in enumerate(key[1:]):
            name = f"_s{i}_{j}_{tag}"
            env[name] = frozenset(t for t, kk in _SCALAR_KEYS.items() if kk == k)
            items.append(f"type({v}[{j}]) in {name}")
        return f"type({v}) is tuple and len({v}) == {len(key) - 1}" + "".join(f" and {t}" for t in items)
    return None


def _jit_view(v: Any) -> Any:
    """What a kernel's JIT copy sees for one of its globals: a kernel's dispatcher for a kernel, and
    for a module of this package that holds kernels (``linalg.cholesky_kernel(...)`` inside a
    kernel) a stand-in module whose kernels are dispatchers, so numba can type the call."""
    if isinstance(getattr(v, "kernel", None), Kernel):
        return v.kernel.jit()
    if isinstance(v, pytypes.ModuleType) and v.__name__.startswith(__package__.partition(".")[0] + "."):
        names = [k for k, a in vars(v).items() if isinstance(getattr(a, "kernel", None), Kernel)]
        if names:
            view = pytypes.ModuleType(v.__name__)
            view.__dict__.update(vars(v))
            view.__dict__.update({k: getattr(v, k).kernel.jit() for k in names})
            return view
    return v


def _first_call(*args: Any, **kwargs: Any) -> Any:
    """The code of a kernel's dispatch before its first call (:meth:`Kernel._first_call_stub`);
    ``_install`` is its kernel's, from the function's own globals."""
    return _install()(*args, **kwargs)  # noqa: F821 - defined in the stub's globals


class Kernel:
    """A kernel on the ahead-of-time path.

    :attr:`dispatch` (what ``@kernel`` returns) tests the arguments against each compiled
    signature in a few attribute reads (a generated function: numba's own dispatcher is C, and a
    generic Python key costs about 1 µs per argument), calls the match, and otherwise looks the
    arguments' types up by key; types the build did not see compile the kernel with numba's JIT.
    """

    def __init__(self, fn: Callable[..., Any], options: dict[str, Any], module: Any, exports: list[list[Any]]) -> None:
        self.py_func = fn
        self.options = options
        self.name = f"{fn.__module__}.{fn.__qualname__}"
        self._exports = [(getattr(module, symbol), _freeze(key)) for symbol, key in exports]
        self._by_key = {key: f for f, key in self._exports}
        self._jit: Any = None
        self.dispatch = self._first_call_stub()

    def _first_call_stub(self) -> Callable[..., Any]:
        """:attr:`dispatch` before its first call: a function that generates the dispatch code
        (:meth:`_make_dispatch`), takes it over as its own (``__code__``, ``__defaults__``) and
        calls it. Generating it (a ``compile`` per kernel, ~0.17 ms) at import cost every process
        that imports the core ~20 ms for ~125 kernels, most of which a process never calls; later
        calls run the generated code itself, through the same function object (the name a module
        bound at import)."""
        fn = self.py_func
        env: dict[str, Any] = {"__builtins__": __builtins__, "_install": self._install}
        stub = pytypes.FunctionType(_first_call.__code__, env, fn.__name__)
        stub.__qualname__, stub.__module__, stub.__doc__ = fn.__qualname__, fn.__module__, fn.__doc__
        stub.__wrapped__ = fn  # type: ignore[attr-defined]
        stub.py_func = fn  # type: ignore[attr-defined]
        stub.kernel = self  # type: ignore[attr-defined]
        return stub

    def _install(self) -> Callable[..., Any]:
        """Give :attr:`dispatch` its generated code (once; a second thread's call finds it done)."""
        stub = self.dispatch
        if stub.__code__ is _first_call.__code__:
            made = self._make_dispatch(stub.__globals__)
            stub.__defaults__ = made.__defaults__
            stub.__code__ = made.__code__
        return stub

    def _make_dispatch(self, env: dict[str, Any] | None = None) -> Callable[..., Any]:
        """The generated dispatch function, its names defined in ``env`` (its globals; a new dict
        by default)."""
        fn = self.py_func
        nargs = fn.__code__.co_argcount
        args = ", ".join(f"a{i}" for i in range(nargs))
        defaults = fn.__defaults__ or ()
        env = {} if env is None else env
        env.update({"_ndarray": np.ndarray, "_slow": self.call_by_key})
        params = [f"a{i}" if i < nargs - len(defaults) else f"a{i}=_default{i}" for i in range(nargs)]
        env.update({f"_default{nargs - len(defaults) + j}": v for j, v in enumerate(defaults)})
        lines = [f"def {fn.__name__}({', '.join(params)}):"]
        for j, (f, key) in enumerate(self._exports):
            tests = [_test_of(i, k, env, str(j)) for i, k in enumerate(key)]
            if len(key) != nargs or any(t is None for t in tests):
                continue
            env[f"_k{j}"] = f
            lines.append(f"    if {' and '.join(tests) or 'True'}:\n        return _k{j}({args})")
        lines.append(f"    return _slow({args})")
        exec("\n".join(lines), env)  # noqa: S102 - a template over the build's own table
        return env.pop(fn.__name__)

    def call_by_key(self, *args: Any) -> Any:
        """The compiled function for these arguments' types, or numba's JIT."""
        f = self._by_key.get(tuple(map(_arg_key, args)))
        if f is None:
            return self.jit()(*args)
        return f(*args)

    def jit(self) -> Any:
        """This kernel as a numba dispatcher (compiled, or loaded from numba's cache, on first call).
        The kernels it calls are swapped for their dispatchers, so numba can compile the calls."""
        if self._jit is None:
            import numba

            fn = self.py_func
            scope: dict[str, Any] = {}
            copy = pytypes.FunctionType(fn.__code__, scope, fn.__name__, fn.__defaults__, fn.__closure__)
            copy.__qualname__, copy.__module__, copy.__doc__ = fn.__qualname__, fn.__module__, fn.__doc__
            self._jit = numba.njit(cache=True, **self.options)(copy)
            scope.update({k: _jit_view(v) for k, v in fn.__globals__.items()})
        return self._jit

    def __repr__(self) -> str:
        return f"<kernel {self.name} ({len(self._exports)} compiled signatures)>"


# --- the ahead-of-time build -----------------------------------------------------------------------


def _type_key(t: Any) -> Any:
    """:func:`_arg_key` of a numba type; None when the build cannot export it."""
    from numba.core import types
    from numba.np import numpy_support

    if isinstance(t, types.Array):
        return ["A", np.dtype(numpy_support.as_dtype(t.dtype)).str, t.ndim, t.layout, t.mutable, t.aligned]
    if isinstance(t, (types.Float, types.Integer, types.Boolean)):
        return str(t)
    if isinstance(t, types.BaseTuple):
        keys = [_type_key(x) for x in t]
        return None if any(k is None for k in keys) else ["T", *keys]
    return None


def _with_contiguous_variants(signatures: list[tuple[Any, ...]]) -> list[tuple[Any, ...]]:
    """The recorded signatures, each also with its strided ('A') array arguments C-contiguous (in
    every combination, up to three such arguments): a column slice of a 1-row array is contiguous,
    so a call sometimes passes one. Each variant is compiled as numba's JIT would compile it."""
    from itertools import combinations

    from numba.core import types

    out: list[tuple[Any, ...]] = []
    for sig in signatures:
        strided = [i for i, t in enumerate(sig) if isinstance(t, types.Array) and t.layout == "A"][:3]
        for r in range(len(strided) + 1):
            for picked in combinations(strided, r):
                variant = tuple(t.copy(layout="C") if i in picked else t for i, t in enumerate(sig))
                if variant not in out:
                    out.append(variant)
    return out


def _caller(disp: Any, nargs: int) -> Callable[..., Any]:
    """``lambda a0, …: disp(a0, …)``: what pycc exports, so that ``disp`` is compiled with its own
    options (pycc compiles an exported function with default ones: no ``fastmath``, ``error_model``)."""
    args = ", ".join(f"a{i}" for i in range(nargs))
    scope: dict[str, Any] = {"_kernel": disp}
    exec(f"def call({args}):\n    return _kernel({args})\n", scope)  # noqa: S102 - a fixed template
    return scope["call"]


def _build_marker() -> int:  # pragma: no cover - compiled; exported as build_<token>
    return 0


def build(workload: Callable[[], object], verbose: bool = False) -> Path:
    """Compile every kernel ahead of time into ``labelaudit/_kernels_aot*.so`` (and its table).

    ``workload`` runs what the commands run, in this process, so every kernel is imported and
    compiled at the argument types it is called with (:func:`labelaudit.kernels.__main__.workload`).
    Runs in a process on the JIT path (``python -m labelaudit.kernels build`` sets it); takes about
    half a minute. Returns the path of the table.
    """
    if _choose()["mode"] != "jit":
        raise RuntimeError(f"build on the JIT path: run it as {MODE_ENV}=jit python -m labelaudit.kernels build")
    import shutil

    from numba.pycc import CC

    workload()  # imports every module with a kernel the commands run
    cc = CC(AOT_NAME, source_module=__name__)
    cc.target_cpu = "host"  # as numba's JIT: the same instructions, so the same results
    token = os.urandom(8).hex()  # names this build in the module and in its table
    cc.export(f"build_{token}", "i8()")(_build_marker)
    table: dict[str, list[list[Any]]] = {}
    n = 0
    for name, disp in sorted(_REGISTRY.items()):
        if disp.targetoptions.get("inline") == "always":
            continue
        for sig in _with_contiguous_variants(disp.signatures):
            keys = [_type_key(t) for t in sig]
            if any(k is None for k in keys):
                continue
            disp.compile(sig)  # (a variant's first compile; the others are there)
            symbol = f"k{n}_{disp.py_func.__name__}"
            cc.export(symbol, disp.overloads[sig].signature)(_caller(disp, len(sig)))
            table.setdefault(name, []).append([symbol, keys])
            n += 1
    # every module that holds a kernel (an exported one, or one compiled into it), so editing any of them retires the build
    modules = {disp.py_func.__module__ for disp in _REGISTRY.values()}
    sources = sorted(
        {str(Path(sys.modules[m].__file__).resolve().relative_to(_PACKAGE_DIR)) for m in modules} | {_SELF}
    )
    with tempfile.TemporaryDirectory(prefix="labelaudit-kernels-") as tmp:
        cc.output_dir = tmp
        cc.verbose = verbose
        cc.compile()
        built = Path(tmp) / cc.output_file
        staged = _PACKAGE_DIR / f".{cc.output_file}.tmp"
        shutil.copyfile(built, staged)
        os.chmod(staged, 0o755)
        os.replace(staged, _PACKAGE_DIR / cc.output_file)  # atomic: a running process keeps its mapped copy
    from datetime import datetime, timezone

    doc = {
        "fingerprint": fingerprint(sources),
        "token": token,
        "sources": sources,
        "built": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "numba": __import__("numba").__version__,
        "functions": n,
        "kernels": table,
    }
    staged_table = _TABLE.with_suffix(".json.tmp")
    staged_table.write_text(json.dumps(doc, indent=1), encoding="utf-8")
    os.replace(staged_table, _TABLE)
    return _TABLE
