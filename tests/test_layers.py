"""The package's layers point down only, and a module uses other modules' public names only.

An ast walk over ``labelaudit/`` (no import: a module that cannot load is still checked) that
counts every import statement wherever it stands — module level, inside a function (the lazy
imports that keep start-up fast), under ``if TYPE_CHECKING`` — and ``importlib.import_module`` of a
literal name. The layers, bottom to top (docs/architecture.md):

====  ==========  ====================================================================
 0    base        ``constants``, ``errors``, the package root ``labelaudit/__init__.py``
 1    kernels     ``kernels`` (the compiled-loop decorator: imports NumPy only)
 2    core        ``core/`` (the science: arrays in, arrays out)
 3    io          ``config``, ``datasets/``, ``results``, ``executors``
 4    jobs        ``infer/``, ``evaluate/``, ``training``, ``export``, ``rank``, ``gate``, ``summary``, ``review``
 5    views       ``viz/``, ``sim/``, ``demo``
 6    cli         ``cli/``
 7    programs    every ``__main__.py`` (run, never imported)
====  ==========  ====================================================================

Rules:

1. A module imports modules of its own layer or lower ones only.
2. Within a layer, a module may import a module of another package of the same layer (``demo``
   runs ``sim`` and ``viz``), but the packages of one layer never import each other both ways:
   peers build on each other in one direction, or they are one package.
3. No import cycle between modules, lazy imports included (a cycle is a layer in disguise).
4. No module imports, or reads as ``module._name``, another module's underscore name: a name another
   module needs is public in the module that owns it.
5. Every module belongs to a layer: a new top-level module or package is added to :data:`LAYERS`
   (and to the table in docs/architecture.md); a module inside a known package is classified by
   its package.

The package root ``labelaudit/__init__.py`` sits at the bottom because every import of a submodule
runs it first; it therefore imports nothing of the package at load time, and its public names
(``__all__``) reach the modules that own them on first use, by name.
"""

from __future__ import annotations

import ast
import textwrap
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

LAYERS: tuple[tuple[str, frozenset[str]], ...] = (
    ("base", frozenset({"", "constants", "errors"})),  # "" is the package root, labelaudit/__init__.py
    ("kernels", frozenset({"kernels"})),
    ("core", frozenset({"core"})),
    ("io", frozenset({"config", "datasets", "results", "executors"})),
    ("jobs", frozenset({"infer", "evaluate", "training", "export", "rank", "gate", "summary", "review"})),
    ("views", frozenset({"viz", "sim", "demo"})),
    ("cli", frozenset({"cli"})),
    ("programs", frozenset()),  # every __main__ module, whatever its package
)
"""Bottom to top: (layer name, the top-level modules and packages of ``labelaudit`` in it)."""

PROGRAMS = len(LAYERS) - 1


@dataclass(frozen=True)
class Module:
    name: str  # dotted, "labelaudit.core.spatial"
    path: Path
    is_package: bool

    @property
    def unit(self) -> str:
        """The top-level module or package under the root ("" for the root itself)."""
        parts = self.name.split(".")
        return parts[1] if len(parts) > 1 else ""


@dataclass(frozen=True)
class Use:
    source: str  # the importing module
    target: str  # the module imported from
    line: int
    name: str | None = None  # the name taken from ``target`` (None: the module itself)


def collect(root: Path) -> dict[str, Module]:
    """Every ``.py`` module of the package directory ``root`` (its name is the package's)."""
    mods: dict[str, Module] = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).with_suffix("")
        parts = list(rel.parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        mods[".".join(parts)] = Module(".".join(parts), path, is_package)
    return mods


def layer_of(mod: Module) -> int | None:
    """The layer index of a module; None when it belongs to none."""
    if mod.name.rsplit(".", 1)[-1] == "__main__":
        return PROGRAMS
    for i, (_, units) in enumerate(LAYERS):
        if mod.unit in units:
            return i
    return None


def _resolve(mods: dict[str, Module], mod: Module, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    package = mod.name if mod.is_package else mod.name.rpartition(".")[0]
    parts = package.split(".")
    base = parts[: len(parts) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def uses(mods: dict[str, Module], mod: Module, top: str) -> list[Use]:
    """What ``mod`` takes from the package ``top``: modules and names, wherever the import stands."""
    tree = ast.parse(mod.path.read_text(encoding="utf-8"), str(mod.path))
    found: list[Use] = []
    aliases: dict[str, str] = {}  # a local name bound to a package module → that module
    names: dict[str, tuple[str, str]] = {}  # a local name bound to a module's name (a class …) → (module, name)

    def known(name: str) -> bool:
        return name == top or name.startswith(top + ".")

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if known(a.name):
                    found.append(Use(mod.name, a.name, node.lineno))
                    if a.asname:
                        aliases[a.asname] = a.name
                    else:
                        aliases[a.name.split(".")[0]] = a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(mods, mod, node)
            if not known(base):
                continue
            for a in node.names:
                sub = f"{base}.{a.name}"
                if sub in mods:  # `from labelaudit.core import spatial`: the module spatial
                    found.append(Use(mod.name, sub, node.lineno))
                    aliases[a.asname or a.name] = sub
                else:
                    found.append(Use(mod.name, base, node.lineno, a.name))
                    names[a.asname or a.name] = (base, a.name)
        elif isinstance(node, ast.Call):
            f = node.func
            fname = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            if fname in ("import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant):
                target = node.args[0].value
                if isinstance(target, str) and known(target):
                    found.append(Use(mod.name, target, node.lineno))
    # `alias._name`, `alias.Class._name`, `labelaudit.pkg.module._name`: reading a module's private name
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            chain, value = [node.attr], node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if (
                isinstance(value, ast.Name) and value.id in names and value.id not in aliases
            ):  # `Cls._x`, Cls imported by name
                owner, name = names[value.id]
                found.append(Use(mod.name, owner, node.lineno, ".".join([name, *reversed(chain)])))
                continue
            if not (isinstance(value, ast.Name) and value.id in aliases):
                continue
            parts = [aliases[value.id], *reversed(chain[1:])]
            for k in range(len(parts), 0, -1):  # the longest prefix that is a module
                target = ".".join(parts[:k])
                if target in mods:
                    found.append(Use(mod.name, target, node.lineno, ".".join([*parts[k:], node.attr])))
                    break
    return found


_NAMEDTUPLE_API = frozenset(
    {"_fields", "_field_defaults", "_make", "_replace", "_asdict"}
)  # public, despite the underscore


def _private(name: str) -> bool:
    """Whether a (dotted) name has an underscore part that is not a dunder (``_x``, ``Box._x``)."""
    return any(p.startswith("_") and not p.startswith("__") and p not in _NAMEDTUPLE_API for p in name.split("."))


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def check(root: Path) -> list[str]:
    """Every breach of the rules in the package directory ``root``, one readable line each."""
    mods = collect(root)
    top = root.name
    problems: list[str] = []
    layer = {}
    for name, mod in mods.items():
        layer[name] = layer_of(mod)
        if layer[name] is None:
            rel = mod.path.relative_to(root.parent)
            problems.append(
                f"{rel}: '{mod.unit}' is in no layer — add it to LAYERS in tests/test_layers.py "
                f"(and to the layers table of docs/architecture.md)"
            )
    graph: dict[str, set[str]] = defaultdict(set)
    packages: dict[tuple[str, str], Use] = {}
    for name, mod in mods.items():
        rel = mod.path.relative_to(root.parent)
        for u in uses(mods, mod, top):
            target = u.target if u.target in mods else None
            if target is None:
                problems.append(f"{rel}:{u.line}: imports {u.target}, which is not a module of {top}")
                continue
            if u.name is not None and _private(u.name) and target != name:
                problems.append(
                    f"{rel}:{u.line}: uses {target}.{u.name}, a private name of another module "
                    f"— make it public in {target} (or keep the use inside that module)"
                )
            if target == name:
                continue
            graph[name].add(target)
            lo, hi = layer[name], layer[target]
            if lo is None or hi is None:
                continue
            if hi > lo:
                problems.append(
                    f"{rel}:{u.line}: imports {target} (layer {LAYERS[hi][0]}) from layer {LAYERS[lo][0]} "
                    f"— layers point down: {' → '.join(n for n, _ in LAYERS)}"
                )
            elif hi == lo and mods[target].unit != mod.unit:
                packages.setdefault((mod.unit, mods[target].unit), u)
    for (a, b), u in sorted(packages.items()):
        if a < b and (b, a) in packages:
            v = packages[(b, a)]
            problems.append(
                f"{top}.{a} and {top}.{b} (one layer) import each other: {u.source}:{u.line} → {u.target} "
                f"and {v.source}:{v.line} → {v.target} — one of them must not"
            )
    for comp in _cycles(graph):
        problems.append(f"import cycle, lazy imports counted: {', '.join(comp)}")
    root_init = mods.get(top)
    if root_init is not None:
        for u in uses(mods, root_init, top):
            problems.append(
                f"{top}/__init__.py:{u.line}: the package root imports {u.target}; it must import "
                f"nothing of the package (every submodule import runs it first)"
            )
    return list(dict.fromkeys(problems))  # one line per breach, however many names one import takes


# --- the package itself ----------------------------------------------------------------------------


def test_labelaudit_layers_point_down_and_private_names_stay_home() -> None:
    problems = check(REPO / "labelaudit")
    assert not problems, "layer rules broken:\n" + "\n".join(problems)


def test_every_module_has_a_layer_and_the_walk_sees_them_all() -> None:
    mods = collect(REPO / "labelaudit")
    assert len(mods) > 60
    assert {layer_of(m) for m in mods.values()} == set(range(len(LAYERS)))  # every layer is inhabited
    assert layer_of(mods["labelaudit.kernels"]) == 1 and layer_of(mods["labelaudit.core.params"]) == 2
    assert layer_of(mods["labelaudit.__main__"]) == PROGRAMS and layer_of(mods["labelaudit.cli.__main__"]) == PROGRAMS


def test_public_api_names_are_public() -> None:
    """``labelaudit.__all__`` reaches each name in the module that owns it, by its public name."""
    import labelaudit

    for name, owner in labelaudit._EXPORTS.items():  # the root's own table: read here, never by a module
        assert not name.startswith("_") and owner.startswith("labelaudit.")
        assert (REPO / Path(*owner.split("."))).with_suffix(".py").is_file() or (
            REPO / Path(*owner.split(".")) / "__init__.py"
        ).is_file()


# --- the checker fails where it must ---------------------------------------------------------------


def plant(tmp: Path, files: dict[str, str]) -> Path:
    """A small package tree named ``labelaudit`` under ``tmp`` with the given modules."""
    root = tmp / "labelaudit"
    base = {
        "__init__.py": '"""root"""\n',
        "constants.py": "LIMIT = 3\n",
        "kernels.py": "import numpy as np\n",
        "core/__init__.py": "",
        "core/geometry.py": "from labelaudit import constants as C\nfrom labelaudit.kernels import np\n\ndef _helper():\n    return C.LIMIT\n",
        "config.py": "from labelaudit.core import geometry\n",
        "infer/__init__.py": "",
        "infer/run.py": "from labelaudit.config import geometry\n",
        "cli/__init__.py": "",
        "cli/app.py": "def main():\n    from labelaudit.infer import run\n    return run\n",
    }
    for rel, text in {**base, **files}.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(textwrap.dedent(text), encoding="utf-8")
    return root


def test_checker_passes_a_clean_tree(tmp_path: Path) -> None:
    assert check(plant(tmp_path, {})) == []


def test_checker_finds_an_upward_import_even_a_lazy_one(tmp_path: Path) -> None:
    problems = check(
        plant(
            tmp_path,
            {
                "core/geometry.py": """
        import numpy as np

        def box():
            from labelaudit.config import geometry  # inside a function: still an import
            return geometry
    """
            },
        )
    )
    assert len(problems) == 2, problems  # the upward import, and the cycle it closes with config → core
    assert "labelaudit/core/geometry.py:5: imports labelaudit.config (layer io) from layer core" in problems[0]
    assert "import cycle" in problems[1] and "labelaudit.config, labelaudit.core.geometry" in problems[1]


def test_checker_finds_upward_imports_in_every_spelling(tmp_path: Path) -> None:
    spellings = [
        "import labelaudit.infer.run\n",
        "import labelaudit.infer.run as R\n",
        "from labelaudit.infer import run\n",
        "from labelaudit import infer\n",
        "from ..infer.run import geometry\n",
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from labelaudit.infer.run import geometry\n",
        "import importlib\nrun = importlib.import_module('labelaudit.infer.run')\n",
    ]
    for i, text in enumerate(spellings):
        problems = check(plant(tmp_path / str(i), {"core/planted.py": text}))
        assert any("core/planted.py" in p and "(layer jobs) from layer core" in p for p in problems), (text, problems)


def test_checker_finds_a_private_name_taken_from_another_module(tmp_path: Path) -> None:
    for i, text in enumerate(
        [
            "from labelaudit.core.geometry import _helper\n",
            "from labelaudit.core import geometry as G\n\ndef f():\n    return G._helper()\n",
            "import labelaudit.core.geometry\nx = labelaudit.core.geometry._helper\n",
            "from .geometry import _helper\n",
        ]
    ):
        problems = check(plant(tmp_path / str(i), {"core/other.py": text}))
        assert (
            len(problems) == 1
            and "uses labelaudit.core.geometry._helper, a private name of another module" in problems[0]
        ), (text, problems)
    for i, text in enumerate(
        [
            "from labelaudit.core import geometry\nx = geometry.Box._cache\n",
            "from labelaudit.core.geometry import Box\nx = Box._cache\n",
        ]
    ):
        problems = check(plant(tmp_path / f"cls{i}", {"core/other.py": text}))
        assert len(problems) == 1 and "uses labelaudit.core.geometry.Box._cache, a private name" in problems[0], (
            problems
        )
    # dunder names and a module's own private names are not private to someone else
    assert check(plant(tmp_path / "ok", {"core/other.py": "from labelaudit import __doc__\n"})) == []


def test_checker_finds_peers_importing_each_other_and_cycles(tmp_path: Path) -> None:
    problems = check(
        plant(
            tmp_path / "peers",
            {
                "rank.py": "def f():\n    from labelaudit import gate\n",
                "gate.py": "from labelaudit.infer import run\nfrom labelaudit import rank\n",
            },
        )
    )
    assert any("labelaudit.gate and labelaudit.rank (one layer) import each other" in p for p in problems), problems
    problems = check(
        plant(
            tmp_path / "cycle",
            {
                "infer/a.py": "from labelaudit.infer import b\n",
                "infer/b.py": "def f():\n    from labelaudit.infer import a\n",
            },
        )
    )
    assert problems == ["import cycle, lazy imports counted: labelaudit.infer.a, labelaudit.infer.b"]


def test_checker_names_a_module_without_a_layer(tmp_path: Path) -> None:
    problems = check(
        plant(tmp_path, {"newthing.py": "x = 1\n", "datasets/av9.py": "from labelaudit.core import geometry\n"})
    )
    assert problems == [
        "labelaudit/newthing.py: 'newthing' is in no layer — add it to LAYERS in tests/test_layers.py "
        "(and to the layers table of docs/architecture.md)"
    ]


def test_checker_keeps_the_root_free_of_imports(tmp_path: Path) -> None:
    problems = check(plant(tmp_path, {"__init__.py": "def __getattr__(name):\n    from labelaudit import core\n"}))
    assert any("labelaudit/__init__.py:2: the package root imports labelaudit.core" in p for p in problems), problems


def test_kernels_import_numpy_only() -> None:
    """The compiled-loop decorator imports nothing of the package (and of the outside world only
    NumPy at load time, numba on the JIT path): every core module imports it."""
    mods = collect(REPO / "labelaudit")
    inside = [m for m in mods.values() if m.unit == "kernels" and layer_of(m) != PROGRAMS]
    assert inside
    for m in inside:
        assert uses(mods, m, "labelaudit") == [], m.name
        tree = ast.parse(m.path.read_text(encoding="utf-8"))
        top_level = {a.name.split(".")[0] for n in tree.body if isinstance(n, ast.Import) for a in n.names}
        top_level |= {(n.module or "").split(".")[0] for n in tree.body if isinstance(n, ast.ImportFrom)}
        assert top_level - {"__future__", "numpy"} <= set(__import__("sys").stdlib_module_names), (m.name, top_level)
