"""The core compiled with mpy-cross and run in the real MicroPython VM gives
bit-identical results to CPython, allocates nothing in update(), and compiles
for the RP2040 (armv6m)."""

import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import decay
import sensation_core as sc

from conftest import ROOT, SHARED, UNDER_HEAP_LOCK, compile_mpy, run_mp
from strategies import scenario, skin_model

sys.path.insert(0, str(ROOT / "tests"))
import mp_core_driver  # noqa: E402  (the same driver, run by CPython)

DRIVER = ROOT / "tests" / "mp_core_driver.py"
BATCH = 4  # sequences per hypothesis example
EXAMPLES = 520  # -> 2080 sequences per run


class MicroPythonCore:
    """One long-lived MicroPython process; cases are streamed through it."""

    def __init__(self, micropython, path):
        import os

        env = dict(os.environ, MICROPYPATH=str(path))
        self.p = subprocess.Popen(
            [micropython, str(DRIVER)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, bufsize=1
        )
        self.ready = self.p.stdout.readline().strip()
        self.sent = 0

    def ask(self, line):
        self.p.stdin.write(line + "\n")
        self.p.stdin.flush()
        self.sent += 1
        return self.p.stdout.readline().strip()

    def close(self):
        self.p.stdin.write("\n")
        self.p.stdin.close()
        return self.p.wait(timeout=10)


@pytest.fixture(scope="module")
def mp_core(micropython, core_mpy_dir):
    core = MicroPythonCore(micropython, core_mpy_dir)
    yield core
    assert core.close() == 0
    assert core.sent >= BATCH * EXAMPLES * 0.99, f"only {core.sent} sequences were compared"


def encode(lim, cal, mode, rps, skin=(0, 0, 0)):
    v = [lim.i_min_ua, lim.i_max_ua, lim.t_min_us, lim.t_max_us, lim.q_max_pc]
    v += [cal.i0_ua, cal.t0_us, cal.rp0_ohm, cal.x_star_ohm, cal.y_star_pc, mode, *skin]
    v += ["%d/%d" % r if isinstance(r, tuple) else r for r in rps]  # (rp, ltau_q16): the decay told first
    return " ".join(map(str, v))


def test_the_vm_loads_the_compiled_mpy(mp_core):
    assert mp_core.ready.startswith("READY") and mp_core.ready.endswith(".mpy"), mp_core.ready


@settings(max_examples=EXAMPLES)
@given(st.lists(st.tuples(scenario(max_updates=16), st.sampled_from(sc.MODES)), min_size=BATCH, max_size=BATCH))
def test_bit_identical_to_cpython(mp_core, cases):
    for (lim, cal, rps), mode in cases:
        line = encode(lim, cal, mode, rps)
        assert mp_core.ask(line) == mp_core_driver.run(line), line


@settings(max_examples=EXAMPLES // 4)
@given(st.lists(st.tuples(scenario(max_updates=16), skin_model()), min_size=BATCH, max_size=BATCH))
def test_bit_identical_to_cpython_with_the_skin_model(mp_core, cases):
    """MODE_FAST with a skin model (logs, exponentials and root searches in integers)."""
    for (lim, cal, rps), skin in cases:
        line = encode(lim, cal, sc.MODE_FAST, rps, skin)
        assert mp_core.ask(line) == mp_core_driver.run(line), line


# the decay's log2 tau (Q.16) told before an update: none, anywhere in decay's range, or a skin's (~50 us ... 3 ms)
LTAU = st.one_of(st.just(0), st.integers(1, decay.LTAU_END - 1), st.integers(370000, 760000))


@settings(max_examples=EXAMPLES // 4)
@given(st.lists(st.tuples(scenario(max_updates=16), skin_model(), st.data()), min_size=BATCH, max_size=BATCH))
def test_bit_identical_to_cpython_with_the_decays_tau(mp_core, cases):
    """MODE_FAST with a skin model anchored on the decay's tau (rule 7: skin_tau.anchor_tau) where one is told."""
    for (lim, cal, rps), skin, data in cases:
        rps = [(rp, data.draw(LTAU)) for rp in rps]
        g = data.draw(st.one_of(st.just(None), st.integers(-sc.SKIN_TAU_MAX_Q16, sc.SKIN_TAU_MAX_Q16)))
        line = encode(lim, cal, sc.MODE_FAST, rps, skin) + ("" if g is None else f" T{g}")
        assert mp_core.ask(line) == mp_core_driver.run(line), line


def test_rejections_are_identical(mp_core):
    bad = "100 1000 50 2000 1000000 50 1000 20000 -1000 0 4 0 0 0 20000"  # i0 below i_min
    assert mp_core.ask(bad) == mp_core_driver.run(bad) == "E i0_ua"
    bad = "100 1000 50 2000 1000000 500 1000 20000 -1000 0 5 500 100 14000 20000"  # beta below 0.1
    assert mp_core.ask(bad) == mp_core_driver.run(bad) == "E beta_q16"


HEAP_LOCK_SCRIPT = """
import micropython, sensation_core as sc
c = sc.Controller(500, 20000, 50, 2000, 20000000)
c.calibrate(1000, 1000, 30000, -1670, 186000)


def loop(N):
    n = 0
    rp = 30000
    while n < N:
        if n % 500 == 0:
            c.set_mode(sc.MODES[(n // 500) % len(sc.MODES)])  # every mode, in turn
        if n % 1000 == 0:  # MODE_FAST with and without the skin model
            if n % 2000:
                c.set_skin(500, 36045, 14000, 0)  # (with rule 7's tau gain, its calibration check taken as
                c.skin.tau_checked = 1  # passed: the random taus reach the tau jump)
            else:
                c.set_skin(0, 0, 0)
        rp = 3000 + (rp * 7 + n * 131) % 120000  # wanders over the whole valid range
        if n % 997 == 0:
            rp = 250000  # faults too
        if n % 3:  # the decay's tau told (rule 7's anchor), one update in three none
            c.ltau_q16 = 400000 + (n * 7919) % 320000
            c.skin.tau_checked = 1  # (these random taus disagree: rule 7's strikes would turn tau off)
        c.update(rp)
        sc.rp_from_vp(rp // 10, c.i_ua + 1)
        n += 1
    return n

""" + UNDER_HEAP_LOCK + """

def main():
    n, err = under_heap_lock(loop, 10000)
    print("updates", n, "error", err, "model_jumps", c.model_jumps, "tau_jumps", c.skin.tau_jumps)


main()
"""


def test_update_allocates_nothing_under_heap_lock(micropython, core_mpy_dir, tmp_path):
    """10 000 updates cycling through every mode (set_mode itself runs outside the loop's lock only
    in the sense that it allocates nothing either: it is inside the locked loop here)."""
    script = tmp_path / "heaplock.py"
    script.write_text(HEAP_LOCK_SCRIPT)
    r = run_mp(micropython, script, [core_mpy_dir])
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().startswith("updates 10000 error None"), r.stdout + r.stderr
    w = r.stdout.split()
    assert int(w[-3]) > 100 and int(w[-1]) > 10, r.stdout  # the skin model's jumps, and its tau anchor (two taus agreeing on Cp: fewer), were exercised


def test_heap_lock_harness_detects_an_allocation(micropython, core_mpy_dir, tmp_path):
    """The same harness fails when the loop allocates (a list per update)."""
    script = tmp_path / "heaplock_bad.py"
    script.write_text(HEAP_LOCK_SCRIPT.replace("c.update(rp)", "c.update(rp); [rp]"))
    r = run_mp(micropython, script, [core_mpy_dir])
    assert "updates 0 error memory allocation failed" in r.stdout, r.stdout + r.stderr


def test_shared_compiles_for_rp2040(mpy_cross, tmp_path):
    """mpy-cross -march=armv6m (the RP2040's Cortex-M0+) compiles every shared module."""
    srcs = sorted(SHARED.glob("*.py"))
    assert srcs
    for src in srcs:
        out = compile_mpy(mpy_cross, src, tmp_path, "-march=armv6m")
        data = out.read_bytes()
        assert data[0] == ord("M") and data[1] == 6  # mpy v6
