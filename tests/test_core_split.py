"""The core's modules agree with each other and keep sensation_core's public API.

fast_step.py and skin_model.py keep private copies of a few of the core's constants
(a const() is folded only inside its own module on MicroPython); here they are
checked against sensation_core's, and every public name firmware/, host/, bench/ and
tests/ import from sensation_core is still there."""

import ast

from hypothesis import given, settings
from hypothesis import strategies as st

import fast_step
import fixmath
import sensation_core as sc
import skin_model

from conftest import ROOT, SHARED, UNDER_HEAP_LOCK, run_mp
from strategies import scenario

COPIES = {
    fast_step: {"_ST_OK": sc.ST_OK, "_ST_T_MAX": sc.ST_T_MAX, "_RP_MIN_OHM": sc.RP_MIN_OHM,
                "_RP_MAX_OHM": sc.RP_MAX_OHM, "_SAT30": 2**30 - 1, "_MQ_CAP": 2**29 - 1,
                "_K_QMAX": sc._K_QMAX, "_K_TMAX": sc._K_TMAX, "_K_MQN": sc._K_MQN, "_K_MQD": sc._K_MQD, "_K_B": sc._K_B,
                "_K_I": sc._K_I, "_K_T": sc._K_T, "_K_ST": sc._K_ST, "_K_DR": sc._K_DR, "_K_FJ": sc._K_FJ,
                "_K_MC": sc._K_MC, "_W_BIAS": sc._W_BIAS,
                "_V_ON": skin_model._V_ON, "_V_JUMPED": skin_model._V_JUMPED},
    skin_model: {"_RP_MAX_OHM": sc.RP_MAX_OHM, "_SAT30": 2**30 - 1, "_MQ_CAP": 2**29 - 1,
                 "_KB_I": sc._K_B + fast_step._B_I, "_KB_T": sc._K_B + fast_step._B_T,
                 "_KB_RP": sc._K_B + fast_step._B_RP, "_KC_I": sc._K_I, "_KC_T": sc._K_T, "_KC_ST": sc._K_ST,
                 "_KC_MJ": sc._K_MJ, "_KC_LT": sc._K_LT, "_KC_LTU": sc._K_LTU},
    fixmath: {"_SAT30": 2**30 - 1},
}


def test_the_private_copies_agree_with_the_core():
    for mod, names in COPIES.items():
        for name, want in names.items():
            assert getattr(mod, name) == want, (mod.__name__, name)
    assert sc._MQ_CAP == 2**29 - 1


def test_every_public_name_used_outside_is_importable_from_sensation_core():
    """Every `sc.NAME` (and `from sensation_core import NAME`) in firmware/, host/, bench/,
    tests/ resolves on sensation_core."""
    used = set()
    for folder in ("firmware", "host", "bench", "tests"):
        for src in (ROOT / folder).rglob("*.py"):
            tree = ast.parse(src.read_text())
            aliases = set()
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    aliases |= {a.asname or a.name for a in node.names if a.name == "sensation_core"}
                elif isinstance(node, ast.ImportFrom) and node.module == "sensation_core":
                    used |= {a.name for a in node.names}
            for node in ast.walk(tree):
                if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
                    if not node.attr.startswith("_"):
                        used.add(node.attr)
    assert len(used) > 30
    missing = sorted(n for n in used if not hasattr(sc, n))
    assert not missing, missing


def test_the_api_of_before_the_split_is_all_there():
    names = """VERSION I_LIMIT_UA T_LIMIT_US Q_LIMIT_PC RP_MIN_OHM RP_MAX_OHM X_STAR_MIN_OHM VP_LIMIT_MV
    RP_INVALID RP_OVER ST_OK ST_I_MIN ST_I_MAX ST_T_MIN ST_T_MAX ST_Q_MAX ST_RP_LOW ST_RP_HIGH ST_Q_NONPOS
    ST_UNCALIBRATED ST_BOUND_MASK ST_FAULT_MASK MODE_OPEN_LOOP MODE_CONSTANT_CHARGE MODE_CONSTANT_ENERGY
    MODE_PULSE_WIDTH_LINEAR MODE_AKHTAR MODE_FAST MODES FAST_ELASTICITY_Q12 FAST_MODEL_RAISE_LOG2
    SKIN_RS_MAX_OHM SKIN_BETA_MIN_Q16 SKIN_BETA_MAX_Q16 SKIN_CP_MIN_PF SKIN_CP_MAX_PF rp_from_vp Controller""".split()
    assert not [n for n in names if not hasattr(sc, n)]
    c = sc.Controller(100, 10000, 50, 2000, 10_000_000)
    for m in ("set_limits", "calibrate", "set_mode", "set_skin", "delivered", "stop", "update", "_from_q"):
        assert callable(getattr(c, m)), m
    for a in ("mode", "rp_ohm", "me_ua2ms", "mq_target_fc_per_ohm", "mq_last_fc_per_ohm", "i0_ua", "t0_us",
              "rp0_ohm", "x_star_ohm", "y_star_pc", "i_min_ua", "i_max_ua", "t_min_us", "t_max_us", "q_max_pc",
              "calibrated", "i_ua", "t_us", "status", "fast_jumps", "model_jumps", "skin_rs_ohm", "skin_beta_q16",
              "skin_cp_pf"):
        assert isinstance(getattr(c, a), int), a


def test_the_core_reads_on_a_few_screens():
    """issue 14: the paper's law in a file of at most ~450 lines, MODE_FAST beside it."""
    assert len((SHARED / "sensation_core.py").read_text().splitlines()) <= 450
    src = (SHARED / "sensation_core.py").read_text()
    for moved in ("_rp_model", "_root", "_LOG_TAB", "_EXP_TAB", "_drift", "_model_pulse"):
        assert moved not in src, moved


# ---- the law's constants as update reads them (Controller._k, viper) ----

def words(c):
    """What Controller._k must hold, from the attributes of the same meaning."""
    me = c.i0_ua * c.i0_ua * c.t0_us
    return {sc._K_MODE: c.mode, sc._K_IMIN: c.i_min_ua, sc._K_IMAX: c.i_max_ua, sc._K_TMIN: c.t_min_us,
            sc._K_TMAX: c.t_max_us, sc._K_QMAX: c.q_max_pc, sc._K_I0: c.i0_ua if c.calibrated else 0,
            sc._K_T0: c.t0_us, sc._K_RP0: c.rp0_ohm, sc._K_XSN: -c.x_star_ohm, sc._K_ME_HI: me >> 15,
            sc._K_ME_LO: me & 0x7FFF, sc._K_MQN: c._mq_num_pc, sc._K_MQD: c._mq_den_ohm, sc._K_YQ4: c._y_q4,
            sc._K_LCAP: c._line_cap_q4}


@settings(max_examples=300)
@given(scenario(max_updates=4), scenario(max_updates=1), st.sampled_from(sc.MODES))
def test_the_array_update_reads_agrees_with_the_attributes(case, other, mode):
    (lim, cal, rps), (lim2, _, _) = case, other
    c = sc.Controller(lim.i_min_ua, lim.i_max_ua, lim.t_min_us, lim.t_max_us, lim.q_max_pc)
    assert all(c._k[w] == v for w, v in words(c).items() if w in (sc._K_MODE, sc._K_IMIN, sc._K_QMAX, sc._K_I0))
    c.calibrate(cal.i0_ua, cal.t0_us, cal.rp0_ohm, cal.x_star_ohm, cal.y_star_pc)
    c.set_mode(mode)
    assert {w: c._k[w] for w in words(c)} == words(c)
    assert min(c._k) >= 0  # a 64-bit viper reads a ptr32 word unsigned
    for rp in rps:
        c.update(rp)
    assert {w: c._k[w] for w in words(c)} == words(c)
    c.set_limits(lim2.i_min_ua, lim2.i_max_ua, lim2.t_min_us, lim2.t_max_us, lim2.q_max_pc)  # drops the calibration
    assert c._k[sc._K_I0] == 0 and c.update(20000) == sc.ST_UNCALIBRATED
    assert c._k[sc._K_IMIN] == lim2.i_min_ua and c._k[sc._K_QMAX] == lim2.q_max_pc


BEYOND = (2**64 + 1000, -(2**64) + 1000, 2**32 + 1000, -(2**32) + 1000, 2**31 + 20000, 2**30 + 20000,
          2**63 + 20000, 2**40, -(2**40), 2**30 - 1, -(2**30), 499, 500, 200000, 200001, 0, -1)

ODD_RP_SCRIPT = """
import sensation_core as sc
c = sc.Controller(500, 10000, 100, 4000, 30000000)
c.calibrate(1000, 1000, 20000, -1670, 186000)
out = []
for rp in RPS:
    out.append(c.update(rp))
    out.append(c.update(20000))  # (a fault stops the pulse: back to a valid Rp)
print(out)
"""


def test_update_faults_on_every_int_beyond_the_range_as_cpython(micropython, core_mpy_dir, tmp_path):
    """update is viper (machine words): an Rp beyond a word, truncated into [500, 200000] Ohm,
    is still a fault (the echo through _k), on MicroPython as on CPython."""
    script = tmp_path / "odd_rp.py"
    script.write_text(ODD_RP_SCRIPT.replace("RPS", repr(BEYOND)))
    g = {}
    exec(compile(ODD_RP_SCRIPT.replace("RPS", repr(BEYOND)).replace("print(out)", ""), "odd", "exec"), g)
    want = g["out"]
    assert [want[2 * k] for k, rp in enumerate(BEYOND) if not 500 <= rp <= 200000] == \
        [sc.ST_RP_LOW if rp < 500 else sc.ST_RP_HIGH for rp in BEYOND if not 500 <= rp <= 200000]
    r = run_mp(micropython, script, [core_mpy_dir])
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(want)


FRAME_LOCK_SCRIPT = """
import micropython, sensation_core as sc
c = sc.Controller(500, 20000, 50, 2000, 20000000)
c.calibrate(1000, 1000, 30000, -1670, 186000)
assert "update" in c.__dict__  # bound once, on the instance (the frame stores delivered()'s three attributes itself)


def frame(n):
    k = 0
    while k < n:
        c.set_mode(sc.MODES[k % 6])
        c.i_ua = c.i_ua  # the pulse delivered (stim's _control stores these words by ptr32; the setters too allocate nothing)
        c.t_us = c.t_us
        c.update(10000 + (k * 7919) % 90000)
        k += 1
    return k

""" + UNDER_HEAP_LOCK + """

n, err = under_heap_lock(frame, 600)
print("frames", n, "error", err)
"""


def test_delivered_and_update_as_the_frame_calls_them_allocate_nothing(micropython, core_mpy_dir, tmp_path):
    script = tmp_path / "frame_lock.py"
    script.write_text(FRAME_LOCK_SCRIPT)
    r = run_mp(micropython, script, [core_mpy_dir])
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "frames 600 error None", r.stdout + r.stderr


def test_no_unary_minus_or_invert_in_viper_code():
    """MicroPython's native emitter negated (and inverted) a viper int in the register that holds a local, so
    `a = -x` also set x to -x (micropython/micropython#14397, fixed by #19508 after v1.28, the firmware's
    version: the chip has it). The first three locals of a function live in registers: mul_q16(x, b) read
    x's sign after negating it, so on MicroPython mul_q16(-189, 36045) gave +103 (CPython -103): found when
    skin_tau.anchor_tau (I below 1 mA) parted from the host's replay on branch w25 (session 26). Viper code
    writes 0 - x and x ^ -1 instead; this test keeps any unary - or ~ on a variable out of every viper
    function."""
    found = []
    for p in sorted((ROOT / "shared").glob("*.py")) + sorted((ROOT / "firmware").glob("*.py")):
        for f in ast.walk(ast.parse(p.read_text())):
            if isinstance(f, ast.FunctionDef) and any(isinstance(d, ast.Attribute) and d.attr == "viper"
                                                      for d in f.decorator_list):
                found += [f"{p.name}:{n.lineno} {f.name}: {ast.unparse(n)}" for n in ast.walk(f)
                          if isinstance(n, ast.UnaryOp) and isinstance(n.op, (ast.USub, ast.Invert))
                          and not isinstance(n.operand, ast.Constant)]
    assert not found, found


def test_mul_q16_keeps_its_sign_in_the_micropython_vm(micropython, tmp_path):
    """The case that found the emitter's bug above, run in the MicroPython VM (viper as on the chip)."""
    from fixmath import mul_q16

    cases = [(-189, 36045), (189, 36045), (-189, -36045), (189, -36045), (-1, 65536), (-(2**20), 2**16 + 5)]
    script = tmp_path / "m.py"
    script.write_text("from fixmath import mul_q16\nprint([mul_q16(x, b) for x, b in %r])\n" % cases)
    p = run_mp(micropython, script, [SHARED])
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == str([mul_q16(x, b) for x, b in cases]) == "[-103, 103, 103, -103, -1, -1048656]"
