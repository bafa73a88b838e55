"""Ahead-of-time kernels (pipe_nav_core.aot, jit): a command runs them without importing numba,
with results identical to numba's JIT kernels, and any call they do not fit turns the process
to numba instead of computing a wrong answer."""

from __future__ import annotations

import collections
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipe_nav_core import aot, jit

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "bags" / "sample.mcap"

Pair = collections.namedtuple("Pair", "a b")


def _python(code: str, **env: str) -> dict:
    """Run code in a fresh interpreter (the last line it prints is JSON) and parse it."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ, **env}, timeout=600, check=True)  # fmt: skip
    return json.loads(out.stdout.strip().splitlines()[-1])


def _spec(t: str, nd: int = 1, layout: str = "C", ro: bool = False) -> dict:
    return {"k": "a", "dt": t, "nd": nd, "l": layout, "ro": ro}


def test_the_type_check_is_as_strict_as_numba_dispatch():
    check = aot._checker([_spec("float64"), {"k": "f"}, {"k": "i"}, {"k": "b"}])
    x = np.zeros(3)
    assert check(x, 1.0, 2, True)
    assert check(x, np.float64(1.0), np.int64(2), np.bool_(False))
    assert not check(x, 1, 2, True)  # an int is int64 to numba: another specialization
    assert not check(x, 1.0, 2.0, True)
    assert not check(x, 1.0, True, True)  # a bool is not an int64
    assert not check(x.astype(np.float32), 1.0, 2, True)
    assert not check(x.astype(np.int64), 1.0, 2, True)  # same item size, other dtype
    assert not check(np.zeros((3, 1)), 1.0, 2, True)
    assert not check(np.zeros(6)[::2], 1.0, 2, True)  # not C-contiguous
    ro = np.zeros(3)
    ro.flags.writeable = False
    assert not check(ro, 1.0, 2, True)
    assert not check(list(x), 1.0, 2, True)


def test_named_and_plain_tuples_are_checked_item_by_item():
    nt = {"k": "nt", "cls": f"{__name__}.Pair", "items": [{"k": "f"}, _spec("int64", 2)]}
    check = aot._checker([nt, {"k": "t", "items": [{"k": "f"}, {"k": "f"}]}])
    good = Pair(1.0, np.zeros((2, 2), dtype=np.int64))
    assert check(good, (1.0, 2.0))
    assert not check((1.0, good.b), (1.0, 2.0))  # a plain tuple is not the named one
    assert not check(Pair(1.0, np.zeros((2, 2))), (1.0, 2.0))
    assert not check(good, (1.0, 2.0, 3.0))
    assert not check(good, [1.0, 2.0])


def test_only_layout_and_write_flag_are_coerced():
    specs = [_spec("float64", 2), {"k": "f"}]
    strided = np.arange(12.0).reshape(3, 4)[:, ::2]
    fitted = aot.coerced((strided, 1.0), specs)
    assert fitted is not None and fitted[0].flags.c_contiguous
    np.testing.assert_array_equal(fitted[0], strided)
    ro = np.zeros((2, 2))
    ro.flags.writeable = False
    fitted = aot.coerced((ro, 1.0), specs)
    assert fitted is not None and fitted[0].flags.writeable and fitted[0] is not ro
    assert aot.coerced((strided.astype(np.float32), 1.0), specs) is None
    assert aot.coerced((np.zeros(3), 1.0), specs) is None


def _toy(tmp_path: Path) -> tuple:
    """A toy numba kernel called with a float64 array, that array, the kernel's result, and an
    empty ``__pycache__`` in tmp_path (a package) to build its module into."""
    _skip_without_a_compiler()
    from numba import njit

    @njit
    def scaled(x, k):  # noqa: ANN001, ANN202
        return x * k, np.sum(x)

    x = np.arange(4.0)
    (tmp_path / "__pycache__").mkdir()
    return scaled, x, scaled(x, 2.5)


def _ran(loaded: list, x: np.ndarray, want: tuple) -> int:
    """How many of a kernel's exports take (x, 2.5); each that does must give want."""
    ran = 0
    for check, fn, _, _ in aot.checked(loaded):
        if check(x, 2.5):
            got = fn(x, 2.5)
            np.testing.assert_array_equal(got[0], want[0])
            assert got[1] == want[1]
            ran += 1
    return ran


def test_a_toy_kernel_builds_loads_and_runs_its_export(tmp_path):
    scaled, x, want = _toy(tmp_path)
    scaled(np.arange(4), 2.5)  # an int64 specialization too
    assert aot.build(tmp_path, "stamp", [("toy:scaled", scaled)]) == 2
    module = aot.load(tmp_path, "stamp")
    assert module is not None and len(module.exports["toy:scaled"]) == 2
    assert module.prebuilt is None  # built here
    assert aot.load(tmp_path, "another stamp") is None
    assert _ran(module.exports["toy:scaled"], x, want) == 1


FITTING_FLAGS = aot._PREBUILT_FLAGS | {"sse", "sse2"}


def test_a_prebuilt_module_is_installed_only_where_it_fits(tmp_path, monkeypatch):
    """A toy module built for aot.PREBUILT_CPU, packed as the package's prebuilt one, then
    installed into a package without any module: it runs where the fingerprint and the CPU
    fit, and is left alone, nothing written, where either does not or the file is damaged."""
    scaled, x, want = _toy(tmp_path)
    assert aot.build(tmp_path, "stamp", [("toy:scaled", scaled)], aot.PREBUILT_CPU) == 1
    fp = {"sources": "abc", "abi": "".join(next(tmp_path.glob("__pycache__/kernels-*")).suffixes),
          "numba": "1", "llvmlite": "2", "numpy": "3"}  # fmt: skip
    out = aot.pack_prebuilt(tmp_path, fp)
    shutil.rmtree(tmp_path / "__pycache__")
    monkeypatch.setattr(aot, "_cpu_flags", lambda: FITTING_FLAGS - {"avx2", "fma"})
    assert aot.install_prebuilt(tmp_path, "fresh", fp) == (
        "this CPU lacks avx2 fma, which x86-64-v3 code needs"
    )
    monkeypatch.setattr(aot, "_cpu_flags", lambda: FITTING_FLAGS)
    assert aot.install_prebuilt(tmp_path, "fresh", {**fp, "numba": "1.1"}) == (
        "they are built for numba 1, this install has 1.1"
    )
    assert aot.install_prebuilt(tmp_path, "fresh", {**fp, "sources": "abd"}) == (
        "the kernels' sources have changed since they were built"
    )
    assert not (tmp_path / "__pycache__").exists() or not any((tmp_path / "__pycache__").iterdir())
    packed = (out / "kernels.so.xz").read_bytes()
    (out / "kernels.so.xz").write_bytes(packed[: len(packed) // 2])  # damaged
    assert aot.install_prebuilt(tmp_path, "fresh", fp).startswith("installing them failed (EOF")
    assert [p.name for p in (tmp_path / "__pycache__").iterdir()] == []  # nothing half-written
    (out / "kernels.so.xz").write_bytes(packed)
    assert aot.install_prebuilt(tmp_path / "elsewhere", "fresh", fp) == "the package has none"
    assert aot.install_prebuilt(tmp_path, "fresh", fp) is None
    module = aot.load(tmp_path, "fresh")
    assert module is not None and module.prebuilt == aot.PREBUILT_CPU
    assert aot.load(tmp_path, "stamp") is None
    assert _ran(module.exports["toy:scaled"], x, want) == 1


def _pins() -> dict[str, str]:
    pins = {}
    for line in (ROOT / ".ci" / "constraints.txt").read_text(encoding="utf-8").splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition(";")[0].strip().partition("==")
            pins[name] = version
    return pins


def test_the_prebuilt_module_is_of_these_sources_and_the_pinned_versions():
    """The package's prebuilt module was built from the kernels' sources as they are now, for
    the CPython of this machine kind and the numba, llvmlite and NumPy that .ci/constraints.txt
    pins: so a fresh install with .ci/bootstrap takes it instead of compiling."""
    import sysconfig

    meta = json.loads((jit._PACKAGE / aot.PREBUILT / aot.SIDECAR).read_text(encoding="utf-8"))
    fp = meta["fingerprint"]
    rebuild = "stale: run python -m pipe_nav_core.warmup --prebuild after the warm-up"
    assert fp["sources"] == jit.fingerprint()["sources"], rebuild
    assert {k: fp[k] for k in ("numba", "llvmlite", "numpy")} == _pins(), rebuild
    assert fp["abi"] == sysconfig.get_config_var("EXT_SUFFIX") == ".cpython-311-x86_64-linux-gnu.so"
    assert meta["target"] == aot.PREBUILT_CPU and meta["format"] == aot.FORMAT
    kernels = {e["kernel"] for e in meta["exports"]}
    assert {"filter.epoch:run_epochs", "smooth.rts:_rts_backward"} <= {
        k.removeprefix("pipe_nav_core.") for k in kernels
    }


def test_a_fresh_copy_of_the_package_runs_the_prebuilt_module(tmp_path):
    """The package copied as an installer copies it (no __pycache__) and imported in a fresh
    process: where this machine fits the prebuilt module (this venv's versions are the pinned
    ones and the CPU has AVX2 and FMA), the process runs it without numba, and its kernel
    gives what numba's gives here; where it does not, the process says it has no module."""
    shutil.copytree(jit._PACKAGE, tmp_path / "pipe_nav_core",
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    code = """
import json, sys
from pipe_nav_core import jit
from pipe_nav_core.geo import earth
print(json.dumps({"prebuilt": jit.AOT_PREBUILT, "jit": jit.JIT_REASON, "file": jit.__file__,
                  "misfit": jit.PREBUILT_MISFIT,
                  "numba": "numba" in sys.modules, "g": float(earth._gravity(0.7, 100.0))}))
"""
    r = _python(code, PYTHONPATH=str(tmp_path))
    assert r["file"].startswith(str(tmp_path))
    prebuilt = json.loads((jit._PACKAGE / aot.PREBUILT / aot.SIDECAR).read_text(encoding="utf-8"))
    fits = jit.fingerprint() == prebuilt["fingerprint"] and aot._cpu_flags() >= aot._PREBUILT_FLAGS
    if fits:
        assert r["prebuilt"] and r["jit"] is None and not r["numba"] and r["misfit"] is None
        assert (tmp_path / "pipe_nav_core" / "__pycache__" / aot.SIDECAR).is_file()
    else:
        assert not r["prebuilt"] and r["jit"] == "no ahead-of-time module for these sources"
        assert r["misfit"]  # and it is said why
    from pipe_nav_core.geo import earth

    assert r["g"] == float(earth._gravity(0.7, 100.0))
    said = _version(tmp_path)
    assert said.startswith("pipe-nav ") and ("kernels prebuilt for x86-64-v3" in said) is fits
    # a kernel's source edited in that copy: the prebuilt module no longer serves, and is said so
    with open(tmp_path / "pipe_nav_core" / "geo" / "earth.py", "a", encoding="utf-8") as f:
        f.write("\n# edited\n")
    assert _version(tmp_path).endswith(
        "the prebuilt ones do not serve: the kernels' sources have changed since they were built)"
    )


def _version(where: Path) -> str:
    """``pipe-nav --version`` of the package copied into ``where``."""
    out = subprocess.run([sys.executable, "-m", "pipe_nav_core.app.cli", "--version"],
                         env={**os.environ, "PYTHONPATH": str(where)}, capture_output=True,
                         text=True, timeout=120, check=True)  # fmt: skip
    return out.stdout.strip()


def _aot_built() -> bool:
    return not _python("import json; from pipe_nav_core import jit; "
                       "print(json.dumps(jit.JIT_REASON))")  # fmt: skip


def _skip_without_a_compiler() -> None:
    """Where the warm-up found the AOT module cannot be built (no C compiler: it said so and
    the kernels stay numba's), the tests of what it builds skip, naming why; CI, which has a
    compiler, fails on any skip (PIPE_NAV_REQUIRE_ROS, tests/conftest.py)."""
    from pipe_nav_core import warmup

    try:
        said = warmup._marker().read_text(encoding="utf-8").partition("\n")[2]
    except OSError:
        return
    if said.startswith("aot: failed"):
        pytest.skip(f"this install cannot build the AOT module ({said})")


def test_the_installed_package_has_its_ahead_of_time_kernels():
    """What .ci/bootstrap leaves: a fresh process runs the AOT exports."""
    _skip_without_a_compiler()
    assert _aot_built(), "no AOT module for these sources: run python -m pipe_nav_core.warmup"


SMOOTH = """
import json, sys
from pipe_nav_core import jit
from pipe_nav_core.app import cli
code = cli.main(["smooth", sys.argv[1] if len(sys.argv) > 1 else {bag!r}, "--out", {out!r},
                 "--quiet"])
print(json.dumps({{"code": code, "jit": jit.JIT_REASON, "numba": "numba" in sys.modules,
                  "scipy.linalg": "scipy.linalg" in sys.modules,
                  "lapack": "scipy.linalg.cython_lapack" in sys.modules}}))
"""


def test_the_sample_smooth_runs_without_numba_and_equals_the_jit_kernels(tmp_path):
    _skip_without_a_compiler()
    aot_out, jit_out = tmp_path / "aot", tmp_path / "jit"
    ran = _python(SMOOTH.format(bag=str(SAMPLE), out=f"{aot_out}/"))
    # numba's LAPACK module preloaded on its own: scipy.linalg's package never imported
    assert ran == {"code": 0, "jit": None, "numba": False, "scipy.linalg": False, "lapack": True}
    ran = _python(SMOOTH.format(bag=str(SAMPLE), out=f"{jit_out}/"), PIPE_NAV_KERNELS="jit")
    assert ran["code"] == 0 and ran["numba"] and ran["jit"]
    names = sorted(p.name for p in aot_out.iterdir())
    assert names == sorted(p.name for p in jit_out.iterdir()) and len(names) >= 9
    for name in names:
        assert (aot_out / name).read_bytes() == (jit_out / name).read_bytes(), name


def test_a_call_no_export_fits_turns_the_process_to_numba():
    _skip_without_a_compiler()
    code = """
import json
import numpy as np
import pytest
from pipe_nav_core import jit
from pipe_nav_core.geo import attitude, earth
from pipe_nav_core.filter import epoch
from pipe_nav_core.model import measurements
before = jit.JIT_REASON
stand_in = epoch.literal_unroll is jit.literal_unroll
g = float(earth._gravity(0.7, 100.0))        # an exported specialization
n = attitude.qnormalize((2, 0, 0, 0))  # integers: no export takes them
after = jit.JIT_REASON
g2 = float(earth._gravity(0.7, 100.0))       # now numba's dispatcher
import numba
print(json.dumps({"before": before, "after": after, "g": g, "g2": g2, "n": list(n),
                  "rebound": type(earth._gravity).__name__, "stand_in": stand_in,
                  "unroll": epoch.literal_unroll is numba.literal_unroll,
                  "registry": sorted({type(u[2]).__name__ for u in measurements.UPDATES})}))
"""
    r = _python(code, PIPE_NAV_AOT_DEBUG="1")
    assert r["before"] is None and "qnormalize called with other argument types" in r["after"]
    assert r["g"] == r["g2"] and 9.7 < r["g"] < 9.9
    assert r["n"] == [1.0, 0.0, 0.0, 0.0]
    assert r["rebound"] == "CPUDispatcher"
    # the registry of updates (a tuple of kernels) and numba's literal_unroll rebound too
    assert r["stand_in"] and r["unroll"] and r["registry"] == ["CPUDispatcher"]


def test_an_exports_argument_checks_are_made_at_its_kernels_first_call():
    """Loading the module makes no check (some 0.05 s for all of them, at every start); a
    kernel's first call makes its own, and it runs its export."""
    _skip_without_a_compiler()
    code = """
import json
from pipe_nav_core import jit
from pipe_nav_core.geo import earth
before = [k.exports is not None for k in jit._KERNELS]
g = float(earth._gravity(0.7, 100.0))
made = sorted(k.__qualname__ for k in jit._KERNELS if k.exports is not None)
print(json.dumps({"before": any(before), "kernels": len(before), "made": made,
                  "jit": jit.JIT_REASON, "g": g}))
"""
    r = _python(code)
    assert r["jit"] is None and r["kernels"] > 1 and 9.7 < r["g"] < 9.9
    assert not r["before"] and r["made"] == ["_gravity"]


def test_the_aot_kernels_are_said_in_the_warm_marker(tmp_path, monkeypatch):
    from pipe_nav_core import warmup

    marker = tmp_path / "kernels_warm.txt"
    monkeypatch.setattr(warmup, "_marker", lambda: marker)
    monkeypatch.setattr(jit, "AOT_PREBUILT", False)  # a module built here, not the prebuilt one
    marker.write_text(jit._package_stamp())  # a marker written before the AOT module existed
    assert not warmup.is_warm()
    marker.write_text(f"{jit._package_stamp()}\naot: 12 exports (warm-up {warmup.WARM_UP})")
    assert warmup.is_warm() is jit.AOT_LOADED  # built, and loaded here (else: build again)
    marker.write_text(f"{jit._package_stamp()}\naot: failed (no compiler) (warm-up "
                      f"{warmup.WARM_UP})")  # fmt: skip
    assert warmup.is_warm()  # tried for these sources: the JIT kernels serve
    marker.write_text(f"{jit._package_stamp()}\naot: 12 exports (warm-up 1)")
    assert not warmup.is_warm()  # an older warm-up: its module lacks what this one adds
