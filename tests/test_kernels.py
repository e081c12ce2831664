"""The compiled kernels (labelaudit/kernels/): ahead-of-time and JIT give the same rows, bit for
bit; the ahead-of-time dispatch calls the signature numba would pick, and anything else goes to
numba's JIT; a stale or missing build is never used."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import numpy as np
import pytest

from labelaudit import kernels as K

REPO = Path(__file__).resolve().parents[1]
AOT = K.kernel_mode()[0] == "aot"
needs_aot = pytest.mark.skipif(not AOT, reason=f"ahead-of-time kernels not in use: {K.kernel_mode()[1]}")


def _samples() -> list[object]:
    base = np.arange(24, dtype=np.float64).reshape(4, 6)
    ro = base.copy()
    ro.flags.writeable = False
    return [
        base,
        base.astype(np.float32),
        base.T,
        base[:, ::2],
        base[:, 2],
        base[:1, 2],
        base[0],
        ro,
        base.astype(np.int64),
        base > 3,
        np.zeros((2, 3, 4)),
        np.zeros(0),
        1.5,
        3,
        True,
        np.float64(2.0),
        np.float32(2.0),
        np.int64(4),
        np.int32(4),
        (1.0, 2.0),
        (base, 2),
    ]


def test_the_argument_key_is_the_type_numba_gives():
    numba = pytest.importorskip("numba")
    for value in _samples():
        assert K._arg_key(value) == K._freeze(K._type_key(numba.typeof(value))), value


def _scale(a, s):  # pragma: no cover - compiled
    out = np.empty_like(a)
    for i in range(a.shape[0]):
        out[i] = a[i] * s
    return out


def _scale_by_two(a, s=2.0):  # pragma: no cover - compiled
    return a * s


def _fake_kernel(signatures: list[tuple[object, ...]], fn=_scale) -> K.Kernel:
    """A Kernel whose 'compiled' functions are Python functions that say which signature was picked."""
    numba = pytest.importorskip("numba")
    module = types.SimpleNamespace()
    exports = []
    for j, sample in enumerate(signatures):
        setattr(module, f"k{j}", lambda a, s, _j=j: ("compiled", _j, s))
        exports.append([f"k{j}", [K._type_key(numba.typeof(x)) for x in sample]])
    return K.Kernel(fn, {}, module, json.loads(json.dumps(exports)))


def test_the_dispatch_calls_the_signature_numba_would_pick_and_jit_for_the_rest():
    f8 = np.arange(5.0)
    f4 = f8.astype(np.float32)
    strided = np.arange(10.0)[::2]
    k = _fake_kernel([(f8, 1.0), (f4, 1.0), (strided, 1.0)])
    assert k.dispatch(f8, 2.0) == ("compiled", 0, 2.0)
    assert k.dispatch(f4, np.float64(2.0)) == ("compiled", 1, 2.0)  # a float32 array never takes the float64 code
    assert k.dispatch(strided, 2.0) == ("compiled", 2, 2.0)
    assert k.dispatch(f8[:1], 2.0) == ("compiled", 0, 2.0)  # contiguous, whatever it was cut from
    ro = f8.copy()
    ro.flags.writeable = False
    for a, s in (
        (ro, 2.0),
        (f8, 2),
        (f8.astype(np.int64), 2.0),
        (np.arange(6.0).reshape(2, 3), 2.0),
    ):  # not compiled: numba's JIT
        got = k.dispatch(a, s)
        np.testing.assert_array_equal(got, _scale(np.asarray(a), s))
        assert got.dtype == np.asarray(a).dtype
    assert k._jit is not None


def test_the_dispatch_is_generated_on_its_first_call_into_the_same_function():
    """Before its first call a kernel's dispatch holds only a stub's code (nothing generated at
    import); the first call gives the same function object the generated code, which later calls
    run. A module that bound the name at import keeps calling that one object."""
    f8 = np.arange(5.0)
    k = _fake_kernel([(f8, 1.0)], fn=_scale_by_two)
    dispatch = k.dispatch
    assert dispatch.__code__ is K._first_call.__code__
    assert dispatch.__wrapped__ is _scale_by_two and dispatch.kernel is k and dispatch.__name__ == "_scale_by_two"
    assert dispatch(f8) == ("compiled", 0, 2.0)  # the default, as the generated code passes it
    assert k.dispatch is dispatch and dispatch.__code__ is not K._first_call.__code__
    assert dispatch.__code__.co_argcount == 2 and dispatch.__defaults__ == (2.0,)
    assert dispatch(f8, 5.0) == ("compiled", 0, 5.0)
    generated = dispatch.__code__
    assert k._install() is dispatch and dispatch.__code__ is generated  # once only


class _QuickOnly(K.Kernel):
    def call_by_key(self, *args):
        raise AssertionError("took the keyed lookup")


def test_the_quick_tests_take_equal_dtypes_that_are_other_objects():
    numba = pytest.importorskip("numba")
    module = types.SimpleNamespace(k0=lambda a, s: ("compiled", 0, s))
    k = _QuickOnly(_scale, {}, module, [["k0", [K._type_key(numba.typeof(np.zeros(2))), "float64"]]])
    other = pickle.loads(
        pickle.dumps(np.dtype("<f8"))
    )  # equal to float64, another object (arrays read from files have such)
    assert other is not np.dtype("<f8")
    assert k.dispatch(np.zeros(4, dtype=other), 1.0) == ("compiled", 0, 1.0)
    assert k.dispatch(np.zeros(4), np.float64(1.0)) == ("compiled", 0, 1.0)


def test_the_keyed_lookup_finds_what_the_quick_tests_cannot():
    a = np.arange(3.0)
    k = _fake_kernel([((a, 2.0), 1.0)])  # a tuple holding an array has no quick test
    assert k.dispatch((a, 4.0), 2.0) == ("compiled", 0, 2.0)


def test_a_tuple_of_scalars_takes_the_quick_test_and_only_its_own_types():
    """A tuple of scalars (the posterior's EM constants) is tested inline, element by element, as
    numba types it: a tuple of floats takes the compiled function without the keyed lookup; another
    length, an int among the floats or a list does not."""
    numba = pytest.importorskip("numba")
    key = [K._type_key(numba.typeof((1.0, 2.0, 3.0))), "float64"]
    assert key[0] == ["T", "float64", "float64", "float64"]
    module = types.SimpleNamespace(k0=lambda t, s: ("compiled", 0, s))
    k = _QuickOnly(_scale, {}, module, [["k0", key]])
    assert k.dispatch((1.0, np.float64(2.0), 3.0), 2.0) == ("compiled", 0, 2.0)
    for t in ((1.0, 2.0), (1.0, 2, 3.0), [1.0, 2.0, 3.0], (1.0, 2.0, np.float32(3.0))):
        with pytest.raises(AssertionError, match="keyed lookup"):
            k.dispatch(t, 2.0)


def test_a_default_argument_is_passed_as_numba_would():
    k = _fake_kernel([(np.arange(3.0), 1.0)], fn=_scale_by_two)
    assert k.dispatch(np.arange(3.0)) == ("compiled", 0, 2.0)
    assert k.dispatch(np.arange(3.0), 5.0) == ("compiled", 0, 5.0)


def test_a_missing_or_stale_build_is_not_used(tmp_path, monkeypatch):
    saved = dict(K._STATE)
    try:
        monkeypatch.setattr(K, "_TABLE", tmp_path / "none.json")
        K._STATE.clear()
        monkeypatch.setenv(K.MODE_ENV, "")
        assert K.kernel_mode() == ("jit", "not built (run: python -m labelaudit.kernels build)")
        K._STATE.clear()
        monkeypatch.setenv(K.MODE_ENV, "aot")
        with pytest.raises(ImportError, match="not built"):
            K.kernel_mode()
        stale = tmp_path / "stale.json"
        stale.write_text(json.dumps({"fingerprint": "0" * 64, "sources": ["kernels/__init__.py"], "kernels": {}}))
        monkeypatch.setattr(K, "_TABLE", stale)
        K._STATE.clear()
        monkeypatch.setenv(K.MODE_ENV, "")
        mode, why = K.kernel_mode()
        assert mode == "jit" and "built from other sources" in why
        if AOT:  # a table of another build beside the module (e.g. a build that was interrupted between its two files)
            other = tmp_path / "other.json"
            doc = json.loads(Path(saved["module"].__file__).with_name(f"{K.AOT_NAME}.json").read_text())
            other.write_text(json.dumps({**doc, "token": "0" * 16}))
            monkeypatch.setattr(K, "_TABLE", other)
            K._STATE.clear()
            mode, why = K.kernel_mode()
            assert mode == "jit" and "does not describe the module" in why
        K._STATE.clear()
        monkeypatch.setenv(K.MODE_ENV, "jit")
        assert K.kernel_mode() == ("jit", f"{K.MODE_ENV}=jit")
    finally:
        K._STATE.clear()
        K._STATE.update(saved)


def test_the_fingerprint_follows_every_source_byte(tmp_path, monkeypatch):
    monkeypatch.setattr(K, "_PACKAGE_DIR", tmp_path)
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "b.py").write_text("y = 2\n")
    before = K.fingerprint(["a.py", "b.py"])
    assert K.fingerprint(["b.py", "a.py"]) == before
    (tmp_path / "b.py").write_text("y = 3\n")
    assert K.fingerprint(["a.py", "b.py"]) != before


_ROWS = textwrap.dedent("""
    import pickle, sys
    import numpy as np
    from labelaudit.config import resolve_config
    from labelaudit.datasets import Frame
    from labelaudit.infer.rows import process_frame
    from labelaudit.kernels import kernel_mode
    from labelaudit.sim.dataset import simulate_frame

    out = {"mode": kernel_mode()[0]}
    for index in (0, 1):
        sim = simulate_frame(index, seed=7)
        ids = [str(i) for i in range(len(sim.written_boxes))]
        for fmt, classes in (("kitti", ("Car", "Van", "Truck", "Pedestrian", "Cyclist")), ("waymo", ("Vehicle", "Pedestrian", "Cyclist"))):
            mask = np.arange(len(sim.points)) % 3 != 0 if fmt == "waymo" else None
            names = [n if fmt == "kitti" or n in classes else "Vehicle" for n in sim.scene.class_names]
            for model in ("bev", "3d"):
                cfg = resolve_config(None, fmt, classes, model)
                frame = Frame(f"{index}", sim.points, sim.written_boxes, names, ids, ray_mask=mask)
                out[(index, fmt, model)] = process_frame(frame, cfg)
    sys.stdout.buffer.write(pickle.dumps(out))
""")


def _rows(mode: str) -> dict:
    env = {**os.environ, K.MODE_ENV: mode}
    done = subprocess.run(
        [sys.executable, "-c", _ROWS], capture_output=True, env=env, cwd=REPO, timeout=600, check=True
    )
    return pickle.loads(done.stdout)


@needs_aot
def test_ahead_of_time_and_jit_rows_are_bit_identical():
    aot, jit = _rows("aot"), _rows("jit")
    assert (aot.pop("mode"), jit.pop("mode")) == ("aot", "jit")
    assert aot.keys() == jit.keys()
    for key in aot:
        assert pickle.dumps(aot[key]) == pickle.dumps(jit[key]), key  # every value, NaNs included, bit for bit
        assert any(r["status"] == "ok" for r in aot[key][0])


@needs_aot
def test_a_worker_on_the_ahead_of_time_path_never_imports_numba():
    code = (
        "import sys; from labelaudit.constants import WORKER_PRELOAD; import importlib; "
        "[importlib.import_module(m) for m in WORKER_PRELOAD]; "
        "print(sorted(m for m in ('numba', 'llvmlite', 'scipy.linalg') if m in sys.modules))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120, check=True
    )
    assert done.stdout.strip() == "[]"


def test_the_status_command_names_the_path():
    done = subprocess.run(
        [sys.executable, "-m", "labelaudit.kernels", "status"],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
        check=True,
    )
    assert done.stdout.split(":")[0] in ("aot", "jit")


@needs_aot
def test_a_kernel_fallen_to_the_jit_can_call_another_modules_kernels():
    """A call with argument types the build never saw compiles that kernel with the JIT; the kernels
    it reaches through a module of the package (``linalg.cholesky_kernel`` inside the fit's solve)
    are dispatchers there too, so the call is compiled, not refused by numba's typing."""
    from labelaudit.core import fit

    M = np.asfortranarray(
        np.diag([4.0, 16.0, 64.0])
    )  # column-major: a layout the build never exports; exact square roots
    x = fit._solve_spd(M, np.ones(3))
    assert np.array_equal(x, [0.25, 0.0625, 0.015625])
