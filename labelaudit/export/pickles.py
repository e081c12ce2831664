"""Infos pickles: a restricted loader and an atomic writer whose files NumPy 1.x and 2.x both load.

Infos files come from elsewhere, so they are read with an unpickler that resolves only numpy
arrays, dtypes and scalars and builtin containers (:data:`ALLOWED_GLOBALS`). Written files name
numpy's array reconstructor by its ``numpy.core.multiarray`` path, which every NumPy imports
(NumPy 2's own ``numpy._core`` path does not exist in NumPy 1), with a protocol every Python 3
that runs OpenPCDet reads (:data:`labelaudit.constants.INFOS_PICKLE_PROTOCOL`).
"""

from __future__ import annotations

import io
import os
import pickle
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Sequence

from labelaudit import constants as C
from labelaudit import results as R
from labelaudit.errors import ExportError, UnsafePickleError

__all__ = ["ALLOWED_GLOBALS", "dump_infos", "dump_infos_all", "load_infos"]

ALLOWED_GLOBALS = frozenset(
    {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy.core.numeric", "_frombuffer"),
        ("numpy._core.numeric", "_frombuffer"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("collections", "OrderedDict"),
        ("builtins", "set"),
        ("builtins", "frozenset"),
        ("builtins", "slice"),
        ("builtins", "complex"),
        ("builtins", "bytearray"),
    }
)
"""Globals an infos pickle may reference: numpy arrays, dtypes and scalars, and builtin containers."""


class _InfosUnpickler(pickle.Unpickler):
    def __init__(self, file: io.BufferedIOBase, source: str) -> None:
        super().__init__(file)
        self.source = source

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in ALLOWED_GLOBALS:
            raise UnsafePickleError(
                f"{self.source}: refused to load the global {module}.{name}: an infos file holds only numpy arrays, "
                "numbers, strings and containers; this pickle is not an infos file or was tampered with"
            )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # numpy.core.* names of NumPy-1 pickles
            return super().find_class(module, name)


def load_infos(path: str | Path) -> Any:
    """Load an OpenPCDet or mmdet3d infos pickle with the restricted unpickler.

    Raises
    ------
    UnsafePickleError
        The pickle references a global outside :data:`ALLOWED_GLOBALS`.
    ExportError
        Missing or unreadable file, not a pickle.
    """
    path = Path(path)
    if not path.is_file():
        raise ExportError(f"{path}: infos file not found")
    try:
        with open(path, "rb") as f:
            return _InfosUnpickler(f, str(path)).load()  # type: ignore[arg-type]
    except UnsafePickleError:
        raise
    except (
        pickle.UnpicklingError,
        EOFError,
        ValueError,
        TypeError,
        AttributeError,
        ImportError,
        IndexError,
        KeyError,
        OSError,
    ) as exc:
        raise ExportError(f"{path}: not a readable infos pickle ({type(exc).__name__}: {exc})") from None


# --------------------------------------------------------------------------- infos pickles: writing


@contextmanager
def _numpy1_global_names() -> Iterator[None]:
    """Pickle NumPy-2 arrays and scalars under their ``numpy.core.multiarray`` names while inside.

    NumPy 2 pickles name ``numpy._core.multiarray._reconstruct``, which NumPy < 1.26 cannot import;
    ``numpy.core.multiarray`` holds the same two functions in every NumPy (1.x, and 2.x's
    compatibility module), so the file loads everywhere. Their ``__module__`` is set for the
    duration of the dump only (the C pickler takes the name from it) and restored afterwards.
    """
    import numpy.core.multiarray as legacy  # noqa: F401 - must resolve for the pickler's identity check

    funcs = [f for f in (getattr(legacy, "_reconstruct", None), getattr(legacy, "scalar", None)) if f is not None]
    saved = [f.__module__ for f in funcs]
    try:
        for f in funcs:
            f.__module__ = "numpy.core.multiarray"
        yield
    finally:
        for f, m in zip(funcs, saved):
            f.__module__ = m


def dump_infos(obj: Any, path: str | Path) -> Path:
    """Pickle ``obj`` to ``path`` atomically (temporary file + rename), loadable with NumPy 1.x and 2.x."""
    return dump_infos_all([(obj, path)])[0]


def dump_infos_all(items: Sequence[tuple[Any, str | Path]]) -> list[Path]:
    """Pickle several objects like :func:`dump_infos`, all or none.

    Every object is written to a temporary name beside its target first; only when all are
    written are they renamed over their targets. A failure in any write removes the temporaries
    and leaves every target as it was (files that belong together, such as infos and their
    gt-database infos, never end up one new and one old).
    """
    staged: list[tuple[Path, Path]] = []
    try:
        for obj, path in items:
            path = Path(path)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}{R.TMP_MARKER}{os.getpid()}")
            staged.append((tmp, path))
            with open(tmp, "wb") as f, warnings.catch_warnings(), _numpy1_global_names():
                warnings.simplefilter("ignore", DeprecationWarning)
                pickle.dump(obj, f, protocol=C.INFOS_PICKLE_PROTOCOL)
        for tmp, path in staged:
            os.replace(tmp, path)
    finally:
        for tmp, _ in staged:
            if tmp.exists():
                tmp.unlink()
    return [path for _, path in staged]
