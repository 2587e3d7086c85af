"""The integer core against the exact (Fraction) reference of the same law."""

import itertools

from fractions import Fraction

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

import fixmath
import sensation_core as sc
from steadytouch.reference import Calibration, Limits, exact_step, float_steps

from strategies import WIDE, calibration, limits, rp_valid, scenario


def check_invariants(c: sc.Controller, lim: Limits) -> None:
    """Safety: whatever the inputs, no output beyond the limits."""
    assert c.status == c.status & (sc.ST_BOUND_MASK | sc.ST_FAULT_MASK)
    if c.status & sc.ST_FAULT_MASK:
        assert c.i_ua == 0 and c.t_us == 0
        return
    assert lim.i_min_ua <= c.i_ua <= lim.i_max_ua
    assert lim.t_min_us <= c.t_us <= lim.t_max_us
    assert c.i_ua * c.t_us <= lim.q_max_pc


def clear_of_branch_edges(ex, lim: Limits, cal: Calibration) -> bool:
    """True when every bound decision of the exact law is >= 1 unit from its edge,
    so the core (which decides on values within 0.65 of exact) takes the same branch."""
    me = Fraction(cal.me)
    if abs(ex.q_hat_pc - lim.q_max_pc) < 1:
        return False
    tf, i = ex.t_free_us, ex.i_free_ua
    if abs(tf - lim.t_max_us) < 1 or abs(tf - lim.t_min_us) < 1:
        return False
    if tf > lim.t_max_us:
        i = min(ex.q_hat_pc, lim.q_max_pc) / lim.t_max_us
    elif tf < lim.t_min_us:
        i = (me / lim.t_min_us) ** 0.5
    # at the duration ceiling the core's I is ceil(Q / t_max) plus up to 1 uA of hysteresis (up to
    # 2 above Q / t_max): within that of a current bound the core may take either side of it
    edge = 2 if tf > lim.t_max_us else 1
    if abs(i - lim.i_min_ua) < edge or abs(i - lim.i_max_ua) < edge:
        return False
    if i < lim.i_min_ua:
        t = me / lim.i_min_ua**2
        if abs(t - lim.t_max_us) < 1 or abs(t - lim.t_min_us) < 1:
            return False
    if ex.status & sc.ST_Q_MAX and not ex.q_hat_pc > lim.q_max_pc:
        return True  # decided on the product; checked separately
    prod = ex.i_ua * ex.t_us
    return abs(prod - lim.q_max_pc) > ex.i_ua + ex.t_us + 2


def check_against_exact(c: sc.Controller, lim, cal, rp, worst=None) -> None:
    ex = exact_step(lim, cal, rp)
    if ex.status & sc.ST_FAULT_MASK:
        assert c.status == ex.status and c.i_ua == 0
        return
    if not clear_of_branch_edges(ex, lim, cal):
        return
    assert c.status == ex.status, (c.status, ex.status)
    err_i = abs(c.i_ua - ex.i_ua)
    assert err_i <= (2 if ex.status & sc.ST_T_MAX else 1), f"I {c.i_ua} vs exact {float(ex.i_ua):.4f}"
    product_limited = ex.status & sc.ST_Q_MAX and not ex.q_hat_pc > lim.q_max_pc
    if product_limited:
        # T is then derived from the delivered integer I: T = floor(q_max / I)
        assert c.t_us == lim.q_max_pc // c.i_ua or (c.t_us == lim.t_min_us and c.i_ua == lim.q_max_pc // lim.t_min_us)
    elif ex.status == sc.ST_T_MAX or ex.status == sc.ST_T_MAX | sc.ST_Q_MAX and ex.q_hat_pc > lim.q_max_pc:
        # the ceiling keeps the charge: I = ceil(Q / t_max), T = round(Q / I) <= t_max
        q = min(ex.q_hat_pc, lim.q_max_pc)  # (I may be 1 uA higher: the ceiling's hysteresis)
        tol = Fraction(c.i_ua, 2) + 1
        if c.t_us == lim.t_min_us:  # T pinned at the floor (t_min near t_max): I is the integer nearest Q / T
            tol = max(tol, Fraction(c.t_us, 2) + 1)
        assert c.t_us <= lim.t_max_us and abs(c.i_ua * c.t_us - q) <= tol
    else:
        err_t = abs(c.t_us - ex.t_us)
        assert err_t <= 1, f"T {c.t_us} vs exact {float(ex.t_us):.4f}"
        if worst is not None and not ex.status:
            worst["i"] = max(worst["i"], float(err_i))
            worst["t"] = max(worst["t"], float(err_t))


def make(lim: Limits, cal: Calibration) -> sc.Controller:
    c = sc.Controller(lim.i_min_ua, lim.i_max_ua, lim.t_min_us, lim.t_max_us, lim.q_max_pc)
    c.calibrate(cal.i0_ua, cal.t0_us, cal.rp0_ohm, cal.x_star_ohm, cal.y_star_pc)
    return c


def test_worked_example_of_the_notes():
    """NOTES.md: I0 = 1 mA, T0 = 1000 us, Rp0 = 20 kohm, gel -> 10 kohm: I = 1.6016 mA, T = 389.8 us."""
    c = make(WIDE, Calibration(1000, 1000, 20000, -1670, 186000))
    assert c.me_ua2ms == 1_000_000  # 1 mA^2 ms
    assert c.mq_target_fc_per_ohm == 37563  # 37.563 pC/ohm = 0.037563 uC/kohm
    assert c.update(10000) == sc.ST_OK
    assert (c.i_ua, c.t_us) == (1602, 390)


def test_calibration_point_is_a_fixed_point():
    c = make(WIDE, Calibration(1000, 1000, 20000, -1670, 186000))
    assert (c.i_ua, c.t_us) == (1000, 1000)
    c.update(20000)
    assert (c.i_ua, c.t_us, c.status) == (1000, 1000, sc.ST_OK)
    assert c.mq_last_fc_per_ohm == c.mq_target_fc_per_ohm


@settings(max_examples=600)
@given(scenario())
# found by hypothesis: T pinned (t_min = t_max) at the duration ceiling; I was ceil(Q / t_max), 64 pC over Q
@example((Limits(1, 126, 65, 65, 8252), Calibration(100, 65, 883, 0, 0), [1095]))
# found by hypothesis: Q / t_max = 106.003 uA, i_min 108: ceil + the hysteresis kept I at 108 and the charge on
# the line (T 7287 us), where the exact law lands on i_min's branch (T from mE: 50 us); a branch edge
@example((Limits(108, 108, 1, 7424, 794365), Calibration(108, 50, 500, 0, 0), [500, 72867]))
def test_core_matches_exact_reference_and_is_safe(case):
    lim, cal, rps = case
    c = make(lim, cal)
    check_invariants(c, lim)
    for rp in rps:
        c.update(rp)
        check_invariants(c, lim)
        check_against_exact(c, lim, cal, rp)


@settings(max_examples=800)
@given(st.data())
@example(None)
def test_interior_within_one_unit(data):
    """With no bound in the way (wide limits), I and T within 1 uA / 1 us of Eq. 4."""
    if data is None:  # the paper's operating point as a fixed example
        cal, rp = Calibration(1000, 1000, 30000, -1670, 186000), 4000
    else:
        cal = data.draw(calibration(WIDE))
        rp = data.draw(rp_valid)
    c = make(WIDE, cal)
    c.update(rp)
    check_invariants(c, WIDE)
    check_against_exact(c, WIDE, cal, rp)


CORNERS = list(
    itertools.product([100, 10000], [50, 2000], [500, 200000], [500, 200000], [-20000, 0], ["0", "mid", "top"])
)


@pytest.mark.parametrize("lim", [WIDE, Limits(500, 20000, 100, 8000, sc.Q_LIMIT_PC), Limits(100, 3000, 50, 1000, 2_000_000)])
def test_envelope_corners(lim):
    """Every corner of the issue's envelope (i0, t0, Rp0, Rp, x*, y*), with three limit sets."""
    checked = 0
    for i0, t0, rp0, rp, x, yk in CORNERS:
        i0 = min(max(i0, lim.i_min_ua), lim.i_max_ua)
        t0 = min(max(t0, lim.t_min_us), lim.t_max_us, lim.q_max_pc // i0)
        q0 = i0 * t0
        y = {"0": 0, "mid": q0 // 2, "top": q0 - 1}[yk]
        cal = Calibration(i0, t0, rp0, x, y)
        c = make(lim, cal)
        c.update(rp)
        check_invariants(c, lim)
        check_against_exact(c, lim, cal, rp)
        checked += 1
    assert checked == len(CORNERS)


def test_bounds_follow_the_discussion():
    """T below t_min: T held, I from mE; I below i_min: I held, T from mE (the Discussion's
    sensation floors); T above t_max: T held, the charge kept on the line; i_max and q_max are safety."""
    cal = Calibration(1000, 1000, 30000, -1670, 186000)
    lim = Limits(500, 5000, 100, 2000, 10_000_000)
    c = make(lim, cal)
    assert c.update(3000) & sc.ST_T_MIN  # gel: T would fall below 100 us
    assert c.t_us == 100 and c.i_ua == 3162  # sqrt(1e9 / 100)
    assert c.update(200000) & sc.ST_T_MAX  # peeled: T would exceed 2000 us
    q_hat = cal.mq * (200000 - cal.x_star_ohm) + cal.y_star_pc
    assert c.t_us == 2000 and c.i_ua == round(q_hat / 2000) == 2685  # I T = Q-hat, not sqrt(1e9 / 2000)
    lim2 = Limits(900, 5000, 100, 8000, 10_000_000)
    c2 = make(lim2, cal)
    assert c2.update(200000) & sc.ST_I_MIN
    assert c2.i_ua == 900 and c2.t_us == 1235  # 1e9 / 900^2
    lim3 = Limits(100, 1200, 100, 8000, 10_000_000)
    c3 = make(lim3, cal)
    st3 = c3.update(5000)
    assert st3 & sc.ST_I_MAX and c3.i_ua == 1200  # mE not kept: T stays at its free value
    lim4 = Limits(100, 5000, 50, 8000, 1_200_000)
    c4 = make(lim4, cal)
    assert c4.update(60000) & sc.ST_Q_MAX and c4.i_ua * c4.t_us <= 1_200_000


@pytest.mark.parametrize(
    "rp, flag",
    [(499, sc.ST_RP_LOW), (-5000, sc.ST_RP_LOW), (0, sc.ST_RP_LOW), (200001, sc.ST_RP_HIGH), (sc.RP_OVER, sc.ST_RP_HIGH)],
)
def test_invalid_rp_faults_and_stops(rp, flag):
    c = make(WIDE, Calibration(1000, 1000, 30000, -1670, 186000))
    assert c.update(rp) == flag
    assert (c.i_ua, c.t_us, c.status) == (0, 0, flag)
    assert c.update(30000) == sc.ST_OK and c.i_ua > 0  # the core itself does not latch


def test_non_positive_q_hat_faults():
    # i0 = t0 = 1, y* = 0: Q = d/d0 pC; with d/d0 < 1/16 the 1/16-pC estimate is 0
    c = make(Limits(1, 20000, 1, 8000, sc.Q_LIMIT_PC), Calibration(1, 1, 200000, 0, 0))
    assert c.update(500) == sc.ST_Q_NONPOS and c.i_ua == 0


def test_update_before_calibrate_faults():
    c = sc.Controller(100, 10000, 50, 2000, 10_000_000)
    assert c.update(20000) == sc.ST_UNCALIBRATED and c.i_ua == 0


@pytest.mark.parametrize(
    "args, name",
    [
        ((0, 1000, 50, 2000, 10**6), "i_min_ua"),
        ((100, 20001, 50, 2000, 10**6), "i_max_ua"),
        ((100, 1000, 50, 8001, 10**6), "t_max_us"),
        ((100, 1000, 60, 50, 10**6), "t_min_us"),
        ((100, 1000, 50, 2000, 2**25 + 1), "q_max_pc"),
        ((100, 1000, 50, 2000, 4999), "q_max_pc"),
    ],
)
def test_constructor_rejects_out_of_range(args, name):
    with pytest.raises(ValueError, match=name):
        sc.Controller(*args)


@pytest.mark.parametrize(
    "cal, name",
    [
        ((50, 1000, 20000, -1000, 0), "i0_ua"),
        ((1000, 3000, 20000, -1000, 0), "t0_us"),
        ((1000, 1000, 499, -1000, 0), "rp0_ohm"),
        ((1000, 1000, 20000, -20001, 0), "x_star_ohm"),
        ((1000, 1000, 20000, 1, 0), "x_star_ohm"),
        ((1000, 1000, 20000, -1000, 1_000_000), "y_star_pc"),
        ((1000, 1000, 20000, -1000, -1), "y_star_pc"),
    ],
)
def test_calibrate_rejects_out_of_range_and_changes_nothing(cal, name):
    c = sc.Controller(100, 10000, 50, 2000, 10_000_000)
    c.calibrate(1000, 1000, 30000, -1670, 186000)
    before = state(c)
    with pytest.raises(ValueError, match=name):
        c.calibrate(*cal)
    assert state(c) == before


def state(c):
    """Every attribute of c, and of the objects it keeps its state in (the skin model and
    the pulses), by value."""
    out = {}
    for k, v in vars(c).items():
        if hasattr(v, "__dict__"):
            out[k] = state(v) if v is not c and k != "c" else "controller"
        else:
            out[k] = v
    return out


def test_rp_from_vp():
    assert sc.rp_from_vp(20000, 1000) == 20000  # 20 V / 1 mA
    assert sc.rp_from_vp(1, 3) == 333
    assert sc.rp_from_vp(2, 3) == 667  # rounded
    assert sc.rp_from_vp(5000, 0) == sc.RP_INVALID
    assert sc.rp_from_vp(-1, 1000) == sc.RP_INVALID
    assert sc.rp_from_vp(sc.VP_LIMIT_MV + 1, 1000) == sc.RP_OVER
    assert sc.rp_from_vp(sc.VP_LIMIT_MV, 1) == sc.VP_LIMIT_MV * 1000  # the limit itself is still a reading
    assert sc.rp_from_vp(0, 1) == 0 and sc.rp_from_vp(1, -5) == sc.RP_INVALID


def test_open_loop_mode_holds_calibration_but_still_faults():
    c = make(WIDE, Calibration(1000, 1000, 30000, -1670, 186000))
    c.set_mode(sc.MODE_OPEN_LOOP)
    assert c.update(10000) == sc.ST_OK and (c.i_ua, c.t_us) == (1000, 1000)
    assert c.update(300000) == sc.ST_RP_HIGH and c.i_ua == 0
    with pytest.raises(ValueError):
        c.set_mode(99)


@settings(max_examples=200)
@given(st.data())
def test_float_reference_agrees_with_exact(data):
    """The numpy float64 reference (used for analysis) is the same law."""
    lim = data.draw(limits())
    cal = data.draw(calibration(lim))
    rps = data.draw(st.lists(rp_valid, min_size=1, max_size=20))
    fl = float_steps(lim, cal, rps)
    for k, rp in enumerate(rps):
        ex = exact_step(lim, cal, rp)
        if not clear_of_branch_edges(ex, lim, cal):
            continue
        assert fl["status"][k] == ex.status
        assert fl["i_ua"][k] == pytest.approx(float(ex.i_ua), rel=1e-9, abs=1e-9)
        assert fl["t_us"][k] == pytest.approx(float(ex.t_us), rel=1e-9, abs=1e-9)


# ---------------------------------------------------------------- every mode
@settings(max_examples=400)
@given(scenario(max_updates=20), st.sampled_from(sc.MODES))
def test_every_mode_obeys_the_safety_invariants(case, mode):
    lim, cal, rps = case
    c = make(lim, cal)
    c.set_mode(mode)
    for rp in rps:
        st_ = c.update(rp)
        check_invariants(c, lim)
        if sc.RP_MIN_OHM <= rp <= sc.RP_MAX_OHM:
            assert not st_ & (sc.ST_RP_LOW | sc.ST_RP_HIGH)
        else:
            assert c.i_ua == 0


@settings(max_examples=300)
@given(st.data())
def test_baseline_laws(data):
    cal = data.draw(calibration(WIDE))
    rp = data.draw(rp_valid)
    c = make(WIDE, cal)
    c.set_mode(sc.MODE_CONSTANT_CHARGE)  # Kantor: I T held (and split as calibrated)
    c.update(rp)
    assert (c.i_ua, c.t_us) == (cal.i0_ua, cal.t0_us)
    c.set_mode(sc.MODE_CONSTANT_ENERGY)  # Tachi: Vp I T = Rp I^2 T held with I = I0
    c.update(rp)
    t_exact = Fraction(cal.t0_us * cal.rp0_ohm, rp)
    assert c.i_ua == cal.i0_ua
    if 1 < t_exact < sc.T_LIMIT_US - 1 and cal.i0_ua * t_exact < sc.Q_LIMIT_PC - cal.i0_ua:
        assert abs(c.t_us - t_exact) <= Fraction(1, 2) + Fraction(1, 100)
    c.set_mode(sc.MODE_PULSE_WIDTH_LINEAR)  # T = T0 + (dT/dRp at Rp0) (Rp - Rp0)
    c.update(rp)
    b = 2 * cal.mq / cal.i0_ua
    t_lin = cal.t0_us + b * (rp - cal.rp0_ohm)
    if 2 < t_lin < sc.T_LIMIT_US - 2 and cal.i0_ua * t_lin < sc.Q_LIMIT_PC - 2 * cal.i0_ua:
        assert abs(c.t_us - t_lin) <= 1


def test_fast_mode_starts_with_the_prior_step_and_then_jumps():
    cal = Calibration(1000, 1000, 30000, -1670, 186000)
    a, f = make(WIDE, cal), make(WIDE, cal)
    f.set_mode(sc.MODE_FAST)
    a.update(20000)
    f.update(20000)  # no secant yet: the Newton step with the least elasticity
    q_k = cal.i0_ua * cal.t0_us
    line = cal.y_star_pc + cal.mq * (20000 - cal.x_star_ohm)  # the paper's step
    g = Fraction(sc.FAST_ELASTICITY_Q12, 4096) * cal.mq * 20000 / q_k
    q_star = (line - g * q_k) / (1 - g)
    assert f.fast_jumps == 1
    assert abs(f.i_ua * f.t_us - q_star) <= f.t_us / 2 + q_star / 2000  # charge-exact pulse
    assert f.i_ua * f.t_us < a.i_ua * a.t_us < q_k  # the paper's direction, further
    # the skin answers the new pulse with a further drop (Rp falls as I rises): the secant jumps further
    a.update(15000)
    f.update(15000)
    assert f.fast_jumps == 2
    assert f.i_ua > a.i_ua and f.t_us < a.t_us  # same direction as the paper, further
    assert f.i_ua ** 2 * f.t_us == pytest.approx(cal.i0_ua**2 * cal.t0_us, rel=0.01)  # still on the mE curve


# ---- MODE_FAST's skin model: the integer functions against floats ----

@settings(max_examples=3000)
@given(st.integers(1, (1 << 30) - 1))
def test_log2q_is_within_1_5_units(x):
    import math

    assert abs(fixmath.log2q(x) - math.log2(x) * 65536) < 1.5


@settings(max_examples=3000)
@given(st.integers(-10 * 65536, 29 * 65536 - 1))
def test_exp2q_is_within_1e_6_then_rounded(lx):
    v = 2.0 ** (lx / 65536)
    assert abs(fixmath.exp2q(lx) - v) <= 1e-6 * v + 0.5


@settings(max_examples=3000)
@given(st.integers(0, sc.SKIN_RS_MAX_OHM), st.integers(sc.SKIN_BETA_MIN_Q16, sc.SKIN_BETA_MAX_Q16),
       st.integers(sc.SKIN_CP_MIN_PF, sc.SKIN_CP_MAX_PF), st.floats(1000, 300000), st.integers(50, 20000),
       st.integers(1, 8000))
def test_the_integer_skin_model_reads_like_the_float_model(rs, beta, cp, s_ohm, i_ua, t_us):
    """Rp within 2 ohm or 5e-4 wherever the model reads a valid Rp (500 ohm ... 200 kohm)."""
    import math

    from steadytouch import skin

    want = float(skin.rp_ohm(i_ua, t_us, rs, beta / 65536, s_ohm, cp))
    if not (sc.RP_MIN_OHM <= want <= sc.RP_MAX_OHM):
        return
    c = sc.Controller(1, 20000, 1, 8000, 10_000_000)
    c.set_skin(rs, beta, cp)
    got = c.skin.rp(round(math.log2(s_ohm) * 65536), round(math.log2(cp) * 65536),
                      round(math.log2(i_ua) * 65536), round(math.log2(t_us) * 65536))
    assert abs(got - want) <= max(2.0, 5e-4 * want), (got, want)


def test_the_skin_model_finds_the_laws_point_of_its_own_skin():
    """On a skin that is exactly the model (float), one model jump lands on the law: the
    pulse after a hydration step is within the pulse's resolution of the Q-Rp line."""
    from steadytouch import skin

    rs, beta, cp, s0 = 500, 0.55, 14000, 34210.0
    c = sc.Controller(100, 10000, 50, 8000, 10_000_000)
    rp0 = round(float(skin.rp_ohm(1000, 1000, rs, beta, s0, cp)))
    c.calibrate(1000, 1000, rp0, -1670, 186000)
    c.set_mode(sc.MODE_FAST)
    c.set_skin(rs, round(beta * 65536), cp)
    assert c.update(rp0) == sc.ST_OK and (c.i_ua, c.t_us) == (1000, 1000)
    s1 = s0 * 0.6  # gel: S falls, Cp stays
    c.update(round(float(skin.rp_ohm(1000, 1000, rs, beta, s1, cp))))
    assert c.model_jumps == 1
    i, t = c.i_ua, c.t_us
    rp = float(skin.rp_ohm(i, t, rs, beta, s1, cp))
    mq = (1000 * 1000 - 186000) / (rp0 + 1670)
    line = 186000 + mq * (rp + 1670)
    assert abs(i * t - line) <= 0.5 * i + 0.5 * t + 0.002 * line, (i, t, line)
    assert abs(i * t - line) < abs(1000 * 1000 - line) / 20  # (the paper's step: 1/(1-G) further)
