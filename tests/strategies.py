"""Hypothesis strategies over the controller's documented envelope."""

from hypothesis import strategies as st

import sensation_core as sc
from steadytouch.reference import Calibration, Limits

WIDE = Limits(1, sc.I_LIMIT_UA, 1, sc.T_LIMIT_US, sc.Q_LIMIT_PC)


@st.composite
def limits(draw):
    if draw(st.booleans()):
        return WIDE
    i_max = draw(st.integers(100, sc.I_LIMIT_UA))
    i_min = draw(st.integers(1, min(i_max, 2000)))
    t_max = draw(st.integers(50, sc.T_LIMIT_US))
    t_min = draw(st.integers(1, min(t_max, 200)))
    q_max = draw(st.integers(max(i_min * t_min, 1), sc.Q_LIMIT_PC))
    return Limits(i_min, i_max, t_min, t_max, q_max)


@st.composite
def calibration(draw, lim: Limits):
    """The issue's envelope, intersected with what the limits accept."""
    i_lo, i_hi = max(100, lim.i_min_ua), min(10000, lim.i_max_ua)
    t_lo, t_hi = max(50, lim.t_min_us), min(2000, lim.t_max_us)
    if i_lo > i_hi:
        i_lo, i_hi = lim.i_min_ua, lim.i_max_ua
    if t_lo > t_hi:
        t_lo, t_hi = lim.t_min_us, lim.t_max_us
    i0 = draw(st.integers(i_lo, i_hi))
    t_top = min(t_hi, lim.q_max_pc // i0)
    if t_top < t_lo:  # the charge ceiling leaves no room here: the smallest pulse
        i0, t0 = lim.i_min_ua, lim.t_min_us
    else:
        t0 = draw(st.integers(t_lo, t_top))
    q0 = i0 * t0
    rp0 = draw(st.integers(sc.RP_MIN_OHM, sc.RP_MAX_OHM))
    x = draw(st.integers(sc.X_STAR_MIN_OHM, 0))
    y = draw(st.one_of(st.integers(0, q0 - 1), st.sampled_from([0, q0 - 1, q0 // 2])))
    return Calibration(i0, t0, rp0, x, y)


rp_valid = st.integers(sc.RP_MIN_OHM, sc.RP_MAX_OHM)
rp_any = st.one_of(rp_valid, st.integers(-(2**20), 2**20), st.sampled_from([sc.RP_MIN_OHM - 1, sc.RP_MAX_OHM + 1, 0]))


@st.composite
def scenario(draw, max_updates=12):
    lim = draw(limits())
    cal = draw(calibration(lim))
    rps = draw(st.lists(st.one_of(rp_valid, rp_any), min_size=1, max_size=max_updates))
    return lim, cal, rps


@st.composite
def skin_model(draw):
    """MODE_FAST's skin model (rs_ohm, beta_q16, cp_pf) over its whole accepted range."""
    import sensation_core as sc

    return (
        draw(st.integers(0, sc.SKIN_RS_MAX_OHM)),
        draw(st.integers(sc.SKIN_BETA_MIN_Q16, sc.SKIN_BETA_MAX_Q16)),
        draw(st.one_of(st.integers(sc.SKIN_CP_MIN_PF, sc.SKIN_CP_MAX_PF), st.integers(5000, 60000))),
    )
