"""skin_tau.anchor_tau: S and Cp from one reading and the monitor's decay after it
(tau = R(I) Cp), in closed form: MODE_FAST's jump anchors on it when the decay's tau is told (rule 7,
docs/controller.md). The model it sets reads the Rp back and has the tau it was given, for skins
across the accepted parameters; its refusals; bit-identical in the MicroPython VM and allocation-free
under the heap lock; and rule 7 on a closed loop."""

import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import sensation_core as sc
import skin_model as sm
from skin_tau import anchor_tau
from fixmath import log2q

from conftest import UNDER_HEAP_LOCK, run_mp


def model(rs, beta_q16):
    c = sc.Controller(100, 10000, 20, 8000, 30000000)
    c.calibrate(1000, 1000, 20000, -1670, 186000)
    c.set_mode(sc.MODE_FAST)
    c.set_skin(rs, beta_q16, 14000)
    return c.skin


def reading(rs, beta_q16, s_ohm, cp_pf, i_ua, t_us):
    """Rp (ohm, rounded) and log2 tau (us, Q.16, rounded) of the model's skin for a pulse."""
    r = s_ohm * (i_ua / 1000) ** (-beta_q16 / 65536)
    tau = r * cp_pf / 1e6
    return round(rs + r * (1 - math.exp(-t_us / tau))), round(math.log2(tau) * 65536), r, tau


@settings(max_examples=400, deadline=None)
@given(rs=st.integers(0, 5000), beta=st.integers(sm.SKIN_BETA_MIN_Q16, sm.SKIN_BETA_MAX_Q16),
       ls=st.floats(10.0, 17.5), lcp=st.floats(math.log2(200), math.log2(1e6)),
       i=st.integers(100, 10000), t=st.integers(20, 8000))
def test_the_model_anchored_on_tau_reads_the_pulse_back_with_that_tau(rs, beta, ls, lcp, i, t):
    m = model(rs, beta)
    rp, ltau, r, tau = reading(rs, beta, 2 ** ls, 2 ** lcp, i, t)
    if rp - rs < 64 or r > 2 ** 19 or rp > sc.RP_MAX_OHM or tau < 2:  # (refused by the anchor, the core or decay)
        return
    assert anchor_tau(m, rp, ltau, i, t) == 1
    # the model set reads the pulse back: Rp within its rounding (1/2 ohm) and the anchor's 2**-16 steps,
    # magnified where the pulse charges Cp fully (z near 1: R from Rp - Rs alone) or barely (z ~ T/tau)
    got = m.rp(m.ls, m.lc, log2q(i), log2q(t))
    z = 1 - math.exp(-t / tau)  # (the model's own evaluation: z to 2**-16, relative 2**-16 / z)
    assert abs(got - rp) <= 1 + rp * (2e-4 + 1.5 / (65536 * z)), (got, rp, z)
    # ... with the tau it was given: log2 R(I) + log2 Cp - log2 1e6
    lr = m.ls - ((log2q(i) - sm._L_1MA) * beta >> 16)
    assert abs(lr + m.lc - sm._L_1E6 - ltau) <= 40, (lr + m.lc - sm._L_1E6 - ltau)  # 40/65536 octave: 0.04 %
    # and the skin's own S, Cp within what Rp's rounding allows (1/2 ohm of Rp - Rs)
    tol = 2e-4 + 1.0 / (rp - rs)
    assert abs(2 ** (lr / 65536) / r - 1) < tol and abs(2 ** (m.lc / 65536) / (2 ** lcp) - 1) < tol + 1e-4


def test_its_copies_of_skin_models_words_and_constants_agree():
    import skin_tau as st

    names = ("_V_RS", "_V_BETA", "_V_LS", "_V_LC", "_V_BIAS", "_L_1E6", "_L_E", "_L_1MA", "_L_Z12", "_L_R_MAX")
    assert [getattr(st, k) for k in names] == [getattr(sm, k) for k in names]
    assert (st._LC_MIN, st._LC_MAX) == (log2q(sm.SKIN_CP_MIN_PF) - 0x30000, log2q(sm.SKIN_CP_MAX_PF) + 0x10000)


def test_what_cannot_be_anchored_sets_nothing():
    m = model(500, 36045)
    rp, ltau, _, _ = reading(500, 36045, 20000, 14000, 1000, 1000)
    assert anchor_tau(m, rp, ltau, 1000, 1000) == 1
    ls, lc = m.ls, m.lc
    assert anchor_tau(m, rp, 0, 1000, 1000) == 0  # no tau read (decay.ltau_q16's 0)
    assert anchor_tau(m, 515, ltau, 1000, 1000) == 0  # Rp - Rs below 16 ohm
    assert anchor_tau(m, rp, 20 << 16, 1000, 20) == 0  # T / tau below 2**-16
    assert anchor_tau(m, rp, ltau + (12 << 16), 1000, 1000) == 0  # Cp 4096 x: above 2 x SKIN_CP_MAX_PF
    assert anchor_tau(m, rp, ltau - (12 << 16), 1000, 1000) == 0  # Cp / 4096: below SKIN_CP_MIN_PF / 8
    assert (m.ls, m.lc) == (ls, lc)  # a refusal leaves the model as it was


DRIVER = """
import sys, json, micropython
sys.path.insert(0, '')
import sensation_core as sc
from skin_tau import anchor_tau
cases = json.loads(sys.stdin.read())
out = []
for rs, beta, rp, ltau, i, t in cases:
    c = sc.Controller(100, 10000, 20, 8000, 30000000)
    c.calibrate(1000, 1000, 20000, -1670, 186000)
    c.set_mode(sc.MODE_FAST)
    c.set_skin(rs, beta, 14000)
    m = c.skin
    out.append([anchor_tau(m, rp, ltau, i, t), m.ls, m.lc])
rs, beta, rp, ltau, i, t = cases[0]
def f(k):
    r = 0
    for _ in range(k):
        r = anchor_tau(m, rp, ltau, i, t)
    return r
r, err = under_heap_lock(f, 50)
print(json.dumps([out, r, err is None]))
"""


def test_bit_identical_in_the_micropython_vm_and_allocation_free(micropython, core_mpy_dir, tmp_path):
    import random

    rng = random.Random(7)
    cases = []
    for _ in range(300):
        rs, beta = rng.randint(0, 5000), rng.randint(sm.SKIN_BETA_MIN_Q16, sm.SKIN_BETA_MAX_Q16)
        i, t = rng.randint(100, 10000), rng.randint(20, 8000)
        rp, ltau, _, _ = reading(rs, beta, 2 ** rng.uniform(10, 17.5), 2 ** rng.uniform(7.6, 20), i, t)
        cases.append([rs, beta, rp, ltau, i, t])
    cases[0] = [500, 36045] + list(reading(500, 36045, 20000, 14000, 1000, 1000)[:2]) + [1000, 1000]
    script = tmp_path / "drv.py"
    script.write_text(UNDER_HEAP_LOCK + DRIVER)
    p = run_mp(micropython, script, [core_mpy_dir], stdin=json.dumps(cases))
    assert p.returncode == 0, p.stderr[-2000:]
    got, r, no_alloc = json.loads(p.stdout.strip().splitlines()[-1])
    want = []
    for rs, beta, rp, ltau, i, t in cases:
        m = model(rs, beta)
        want.append([anchor_tau(m, rp, ltau, i, t), m.ls, m.lc])
    assert got == want
    assert sum(1 for x in want if x[0]) > 200  # most anchored: the comparison is not of refusals
    assert no_alloc and r == want[0][0] == 1


def closed_loop(steps, tau=True, n=12, rs=500, beta=36045, cp_set=14000, gain=1.0, told=None, glitch=None,
                noise=None):
    """MODE_FAST on the model's own skin (exact readings: Rp and log2 tau rounded, tau read x gain), the fitted
    Cp cp_set and rule 7's tau gain told (set_skin's tau_q16; None: the true one, log2 gain); steps: [(S ohm,
    Cp pF)] in turn, n pulses each. Per step the felt mQ error of each pulse (the first pulse is the one read
    on the changed skin) and the controller. glitch (step, pulse, x): that pulse's tau read x; None: the same
    pulse told no tau (the reference for a glitch)."""
    x, y = -1670, 186000
    c = sc.Controller(100, 10000, 20, 8000, 30000000)
    s0, cp0 = steps[0]
    rp0 = reading(rs, beta, s0, cp0, 1000, 1000)[0]
    c.set_mode(sc.MODE_FAST)
    c.set_skin(rs, beta, cp_set, round(math.log2(gain) * 65536) if told is None else told)
    c.ltau_q16 = reading(rs, beta, s0, cp0, 1000, 1000)[1] + round(math.log2(gain) * 65536)  # (the calibration
    c.calibrate(1000, 1000, rp0, x, y)  # pulse's tau: rule 7's check of the gain)
    target = (1000 * 1000 - y) / (rp0 - x)
    out = []
    for s, cp in steps:
        errs = []
        for _ in range(n):
            i, t = c.i_ua, c.t_us
            rp, lt, _, _ = reading(rs, beta, s, cp, i, t)
            errs.append((i * t - y) / (rp - x) / target - 1)
            c.ltau_q16 = lt + round(math.log2(gain) * 65536) if tau else 0
            if noise is not None and c.ltau_q16:  # (noise: a random.Random, tau read x 2**(0.3 N(0, 1)))
                c.ltau_q16 += round(0.3 * noise.gauss(0, 1) * 65536)
            if glitch is not None and (len(out), len(errs) - 1) == glitch[:2]:
                c.ltau_q16 += round(math.log2(glitch[2]) * 65536)
            c.update(rp)
            assert c.ltau_q16 == 0  # (told for one update only)
        out.append(errs)
    return out, c


def test_with_the_decays_tau_a_step_of_the_skin_is_met_by_the_second_corrected_pulse():
    """Rule 7: the jump anchors S and Cp on the reading and its tau once two reads agree on Cp, so a step that
    changes Cp too (gel: S / 3, Cp x 2.5; the fitted Cp that of the dry skin) is met by the second corrected
    pulse (the law on the skin as it is; the first, its tau disagreeing with the dry skin's, is rules 1-6's);
    without tau the model's Cp is inferred and the gel's second pulse is still +7 %."""
    steps = [(30000, 14000), (10000, 35000), (30000, 14000), (16000, 9000)]
    with_tau, c = closed_loop(steps)
    without, c0 = closed_loop(steps, tau=False)
    assert [e[:2] for e in with_tau] == [e[:2] for e in without]  # (the first corrected pulse: rules 1-6)
    for errs in with_tau[1:]:
        assert max(abs(e) for e in errs[2:]) < 0.004, errs  # (the pulse's rounding: 1 uA, 1 us)
    assert c.skin.tau_jumps >= 3 and c0.skin.tau_jumps == 0
    assert max(e[2] for e in without[1:]) > 0.05, [e[:4] for e in without]  # (what rule 7 changes)


@pytest.mark.parametrize("wild", [0.25, 0.5, 2.0, 4.0])
@pytest.mark.parametrize("at", [0, 1])
def test_a_single_wild_tau_never_shapes_the_model(wild, at):
    """One tau read x wild (a glitch on the decay) with the Rp true, on the gel step's first or second pulse (where
    the model jumps): its Cp disagrees with the reads before and after it, so no jump anchors on it (review of
    session 26: on the realistic bench x 0.5 on one pulse felt +16 %, x 0.25 +23 %, where tau-off moved 0.1 %).
    The glitch costs the pulses rules 1-6 take, never more: every pulse after it is felt no further above the
    target than with tau or without it."""
    steps = [(30000, 14000), (10000, 35000)]
    ref, _ = closed_loop(steps)
    off, _ = closed_loop(steps, tau=False)
    out, c = closed_loop(steps, glitch=(1, at, wild))
    assert out != ref  # (the glitch reached a jump)
    for o, r, f in zip(out[1][at + 1:], ref[1][at + 1:], off[1][at + 1:]):
        assert o <= max(r, f) + 1e-9, (out[1], ref[1], off[1])
    assert max(abs(e) for e in out[1][at + 3:]) < 0.004, out[1]


def test_a_decay_read_much_noisier_than_on_the_sweeps_turns_tau_off():
    """tau read x 2**(0.3 N(0, 1)) on every pulse of the run (the sweeps' spread check never saw it: review of
    session 26, 0.2 octave +26 % felt): reads disagree on Cp more often than they agree, and after
    FAST_TAU_STRIKES more disagreements tau is off until the next calibration; the steps are then rules 1-6's."""
    import random

    steps = [(30000, 14000), (10000, 35000), (30000, 14000), (16000, 9000)]
    out, c = closed_loop(steps, noise=random.Random(3))
    off, _ = closed_loop(steps, tau=False)
    assert c.skin.tau_checked == 0
    for o, f in zip(out[1:], off[1:]):  # (the noisy reads before it are used: after the first corrected pulse
        assert max(o[2:]) <= max(max(f[2:]), 0.025), (o, f)  # none felt more than 2.5 % above target where
        # tau-off is within it)
    out, c = closed_loop(steps)  # (the same without noise: on to the end)
    assert c.skin.tau_checked == 1


def test_a_first_tau_after_a_calibration_is_not_anchored_on():
    """The Cp of the first tau after a calibration has nothing to agree with (an earlier arm's skin may not be
    this one's): two reads are needed."""
    c = closed_loop([(30000, 14000)], n=1)[1]
    assert c.skin.tau_jumps == 0


@pytest.mark.parametrize("gain", [0.72, 0.8, 1.25, 1.38])
def test_a_monitor_that_scales_tau_is_taken_out_with_the_gain_set(gain):
    """A decay read x gain on every pulse (a monitor's filter, a lead: review of session 25, x 2 felt +40 %
    when the controller took it as true): the host measures the gain on the calibration sweeps (skin.tau_gain)
    and sends it with the model; taken out of every tau, the steps are met as with a true tau (by the second
    corrected pulse)."""
    steps = [(30000, 14000), (10000, 35000), (30000, 14000), (16000, 9000)]
    out, c = closed_loop(steps, gain=gain)
    assert c.skin.tau_ok == 1 and c.skin_tau_q16 == round(math.log2(gain) * 65536)
    for errs in out[1:]:
        assert max(abs(e) for e in errs[2:]) < 0.004, errs
    assert c.skin.tau_jumps >= 3


@pytest.mark.parametrize("k", [0.8, 1.15, 1.25, 1.38])
def test_a_gain_that_is_not_the_monitors_now_turns_tau_off_at_the_calibration(k):
    """The gain set is stale (a sweeps file of another session, a monitor changed since: the monitor now reads
    tau x k over the gain told, 0): the calibration pulse's tau gives a Cp off the fitted one by more than
    FAST_TAU_AGREE, so tau is not used until the next calibration and the run is the one without tau (review of
    session 26: x 1.15 +8 %, x 1.25 +13 % felt where tau-off kept 4 %)."""
    steps = [(30000, 14000), (10000, 35000), (30000, 14000), (16000, 9000)]
    out, c = closed_loop(steps, gain=k, told=0)
    ref, _ = closed_loop(steps, tau=False)
    assert c.skin.tau_checked == 0 and c.skin.tau_jumps == 0 and out == ref
    out, c = closed_loop(steps, gain=k)  # (the same monitor with its gain told: checked, used)
    assert c.skin.tau_checked == 1 and c.skin.tau_jumps >= 3


def test_tau_off_is_the_run_without_tau_and_a_gain_out_of_range_is_refused():
    """set_skin with SKIN_TAU_OFF (the host's tau_gain did not trust the sweeps' taus, or none were recorded):
    the taus told change nothing, the run is the one told none. A gain past SKIN_TAU_MAX_Q16 is refused,
    nothing changed; a gain with no model is refused too."""
    steps = [(30000, 14000), (10000, 35000), (30000, 14000)]
    out, c = closed_loop(steps, told=sc.SKIN_TAU_OFF)
    ref, _ = closed_loop(steps, tau=False)
    assert c.skin.tau_ok == 0 and c.skin.tau_jumps == 0 and out == ref
    c.set_skin(500, 36045, 14000, 100)
    for bad in (sc.SKIN_TAU_MAX_Q16 + 1, sc.SKIN_TAU_OFF - 1, 0x10000):  # (SKIN_TAU_OFF is -MAX - 1)
        with pytest.raises(ValueError, match="tau_q16"):
            c.set_skin(400, 36045, 15000, bad)
        assert (c.skin_rs_ohm, c.skin_cp_pf, c.skin_tau_q16) == (500, 14000, 100)
    with pytest.raises(ValueError, match="tau_q16=100 with no skin model"):  # (as the device and the host refuse it)
        c.set_skin(0, 0, 0, 100)
    assert c.skin_tau_q16 == 100
    c.set_skin(0, 0, 0)
    assert c.skin_tau_q16 == sc.SKIN_TAU_OFF and not c.skin.tau_ok


def test_a_new_model_without_a_gain_turns_tau_off_and_a_calibration_keeps_it():
    """The gain is the monitor's, measured with a fit: a set_skin without one (another fit) turns tau off; a
    calibration (ARM, SET_MODE while armed) keeps the model's gain."""
    c = closed_loop([(30000, 14000)], gain=1.25)[1]
    g = c.skin_tau_q16
    c.calibrate(1000, 1000, 31000, -1670, 186000)
    assert c.skin_tau_q16 == g and c.skin.tau_ok == 1
    c.set_skin(500, 36045, 14000)
    assert c.skin_tau_q16 == sc.SKIN_TAU_OFF and c.skin.tau_ok == 0


def test_a_jump_without_tau_takes_the_fitted_cp_back():
    """After tau anchors, a jump told no tau starts from the fitted Cp, not from the last anchor's (a wild
    reading with its tau left Cp x 1.75 for the jumps without tau that followed: +12.6 % felt, review of
    session 25)."""
    c = closed_loop([(30000, 14000), (10000, 35000)])[1]
    assert c.skin.lc != c.skin.lc_set  # (the last tau anchor's Cp)
    rp = reading(500, 36045, 16000, 9000, c.i_ua, c.t_us)[0]
    c.update(rp)  # a step, no tau told: rules 1-6
    assert c.skin.lc == c.skin.lc_set  # (before the fix: the anchor's Cp stayed)
