"""fast_step: MODE_FAST's next pulse (docs/controller.md, "MODE_FAST").

The paper's law is the fixed-point iteration Q(k+1) = L(Rp(Q_k)). MODE_FAST reaches
the same fixed point sooner: a Newton step on the loop linearised around the last
pulse (newton), a prediction of a falling drift (fast_pulse's head), the law solved on a skin
model when one is set (skin_model.SkinModel.jump), and a correction when the paper's
step enters the duration ceiling (fast_pulse). It then goes through the very same
Eq. 4 and bounds as the paper's mode (Controller._from_q).

Functions of the Controller `c`, not methods: the core stays the paper's law. State
used here: c.before (the pulse measured before the one just measured) and
c.drift_ohm. The core's Eq. 3 and Eq. 4 come in as arguments (line, from_q:
sensation_core._line, _from_q): this module cannot import the core, which imports it,
and a method call on the Controller costs ~16 us more than a function call on the chip
(its attribute map is large). Every intermediate is below 2**30; nothing is allocated.
"""

try:
    import micropython
    from micropython import const
except ImportError:  # CPython: the decorators do nothing, ptr32 indexes the array itself

    class micropython:  # noqa: N801 (stands in for the module's decorators)
        viper = native = staticmethod(lambda f: f)

    def const(x):
        return x

    def ptr32(a):
        return a


from fixmath import frac12, muldiv, word

# the least elasticity d(ln Rp)/d(ln Q) of the skin along the mE curve, in Q.12
# (0.45: the current exponent beta >= 0.5 less the series resistance)
FAST_ELASTICITY_Q12 = const(1843)
# a large step down on a secant: G from the pair's arc elasticity times this / 8 (1.875),
# at most _G_LOWER_MAX (docs/controller.md, "MODE_FAST": the elasticity grows as the charge
# falls, so the chord under-predicts the fall of Rp and the step lands above the target;
# a stretch this large lands below it on some skins, at a current above the settled one)
FAST_LOWER_STRETCH_Q3 = const(15)

# sensation_core's values: a const() is folded only inside its own module, and importing
# the core's would be a dictionary lookup per use on the chip (and a circular import);
# tests/test_core_split.py checks that they agree.
_ST_OK = const(0)
_ST_T_MAX = const(0x008)
_RP_MIN_OHM = const(500)
_RP_MAX_OHM = const(200000)
_SAT30 = const(0x3FFFFFFF)
_MQ_CAP = const(0x1FFFFFFF)
_K_TMAX = const(4)  # t_max_us
_K_QMAX = const(5)  # words of Controller._k: q_max_pc, mQ's numerator (pC) and denominator (ohm)
_K_MQN = const(12)
_K_MQD = const(13)
_V_ON = const(33)  # words of SkinModel.v: skin_model._V_ON, _V_JUMPED
_V_JUMPED = const(34)
_V_TCK = const(48)  # skin_model._V_TCK: rule 7's calibration of tau (0: under way)
_K_LTU = const(35)  # sensation_core._K_LTU: log2 tau told for this update (0: none)
_NO_G = const(0x8000)  # "no estimate of the loop gain"
_G_MAX = const(3891)  # 0.95 in Q.12: the largest G a step takes (no stable fixed point above)
_G_LOWER_MAX = const(3072)  # 0.75: the largest G the lowering stretch sets (1/(1 - G) <= 4)


# the pulse measured before the one just measured (c.before) lives in five words of the
# controller's int array c._k from _K_B on (sensation_core._K_B): the viper code reads and
# writes them by ptr32; Pulse gives them names
_K_B = const(17)
_K_I = const(22)  # c.i_ua, c.t_us, c.status: words of c._k (properties of the Controller)
_K_T = const(23)
_K_ST = const(24)
_K_DR = const(27)  # c.drift_ohm + _W_BIAS, c.fast_jumps, c.model_cuts (words of c._k too)
_K_FJ = const(28)
_K_MC = const(30)
_W_BIAS = const(0x20000000)
_B_I = const(0)  # i_ua
_B_T = const(1)  # t_us
_B_Q = const(2)  # q_pc = i_ua * t_us
_B_RP = const(3)  # the Rp measured on it; 0: no such pulse (reset)
_B_CLEAN = const(4)  # 1: the step computed from it was clean (no fault, no bound)


class Pulse:
    """A pulse the controller measured Rp on (c.before: the one before the last), as
    attributes: a view on its words in the controller's int array k (_K_B ...)."""

    def __init__(self, k):
        self.v = k  # (fixmath.word reads self.v)

    i_ua = word(_K_B + _B_I)
    t_us = word(_K_B + _B_T)
    q_pc = word(_K_B + _B_Q)
    rp_ohm = word(_K_B + _B_RP)
    clean = word(_K_B + _B_CLEAN)


def least_elastic(x):
    """x * FAST_ELASTICITY_Q12 / 2**12, floored, for 0 <= x < 2**30 (split: < 2**30)."""
    return (x >> 12) * FAST_ELASTICITY_Q12 + (((x & 0xFFF) * FAST_ELASTICITY_Q12) >> 12)


@micropython.viper
def fast_pulse(c, qf: int, q_k: int, rp_ohm: int, line, from_q) -> int:
    """MODE_FAST's next pulse from the paper's step qf (1/16 pC), for the pulse of charge
    q_k just measured (c.i_ua, c.t_us, c.status) with Rp = rp_ohm: the drift
    prediction, then a jump that stays on the path of the measured pulse (mE curve or
    duration ceiling): on the skin model, else a Newton step; else the paper's step,
    corrected when it enters the ceiling from a higher current. line(c, rp) is Eq. 3,
    from_q(c, qf) Eq. 4 with the bounds. Returns the status. (viper: machine integers,
    every value below 2**30; what the calls return is read with int().)"""
    ka = c._k  # (looked up once: the model's jump and ceiling_bound take it too)
    kb = ptr32(ka)  # c.i_ua, c.t_us, c.status and c.before's words
    i_k = kb[_K_I]  # the measured pulse (from_q reads it: restored for a retry)
    t_k = kb[_K_T]
    s_k = kb[_K_ST]
    ceiling = s_k & _ST_T_MAX
    # the drift (inline: a call is ~8 us on the chip): the Rp the law is applied to under a falling
    # drift (sweat, gel soaking in), else rp_ohm. Rp's change since the last pulse less what our own
    # step explains (with the least elasticity) is the skin moving; when it has fallen two pulses
    # running, the law is applied to Rp one pulse ahead (the smaller of the two falls, at most Rp/16).
    # Only falls: a rising drift would raise the charge on a prediction. Sets c.drift_ohm.
    rp_at = rp_ohm
    d_now = 0
    if kb[_K_B + _B_CLEAN] != 0 and q_k > 0:
        dq = q_k - kb[_K_B + _B_Q]
        adq = dq if dq >= 0 else 0 - dq
        if adq < (q_k >> 5):  # a small step of our own (a large one is a jump: not drift)
            f = int(frac12(adq, q_k))  # |dQ|/Q in Q.12, < 128
            x = (rp_ohm >> 12) * f + (((rp_ohm & 0xFFF) * f) >> 12)
            # least_elastic: e Rp |dQ| / Q
            e = (x >> 12) * FAST_ELASTICITY_Q12 + (((x & 0xFFF) * FAST_ELASTICITY_Q12) >> 12)
            d_now = rp_ohm - kb[_K_B + _B_RP] - (e if dq >= 0 else 0 - e)
    d_prev = kb[_K_DR] - _W_BIAS  # (c.drift_ohm)
    kb[_K_DR] = d_now + _W_BIAS
    if d_now < 0 and d_prev < 0:
        d = d_now if d_now > d_prev else d_prev  # the smaller fall
        if 0 - d >= (rp_ohm >> 9):  # below 0.2 %: the quantisation of Rp and of the pulse, not drift
            if 0 - d > (rp_ohm >> 4):
                d = 0 - (rp_ohm >> 4)
            if rp_ohm + d >= _RP_MIN_OHM:
                rp_at = rp_ohm + d
    if rp_at != rp_ohm:
        qf = int(line(c, rp_at))
    model = c.skin
    vm = ptr32(model.v)  # (model.jumped, model.on: words of model.v, skin_model._V_JUMPED, _V_ON)
    jumped = vm[_V_JUMPED]
    vm[_V_JUMPED] = 0
    if vm[_V_TCK] == 0 and vm[_V_ON] != 0 and q_k > 0 and kb[_K_LTU] > 0:
        model.check_tau(rp_ohm, kb[_K_LTU], i_k, t_k)  # rule 7: the first taus after a calibration, on its skin
    # on the line within the pulse's resolution (1/2 uA and 1/2 us; at the ceiling,
    # where I and T are split for the charge, 1/2 us): the paper's step
    dq = qf - (q_k << 4)  # 1/16 pC
    if (dq if dq >= 0 else 0 - dq) >= (i_k + (0 if ceiling else t_k)) << 3:
        if vm[_V_ON] != 0 and q_k > 0:
            st = int(model.jump(qf, q_k, rp_at, i_k, t_k, jumped, ka, from_q))  # (c._k: c.before's words)
            if st >= 0:
                return st
            kb[_K_I] = i_k  # the measured pulse back (three stores: cheaper than a call)
            kb[_K_T] = t_k
            kb[_K_ST] = s_k
            if st == -2:  # the model ran out of its work per pulse: the paper's step when
                n = kb[_K_MC]  # (c.model_cuts) it lowers the charge, else the charge held
                if n < _SAT30:
                    kb[_K_MC] = n + 1
                base = q_k << 4
                if qf > base and ceiling == 0:  # a rise on the mE curve: the paper's step (it does not pass
                    st = int(from_q(c, qf))  # the law's stable fixed point there), unless it enters the ceiling
                    if (st & _ST_T_MAX) == 0:
                        return st
                    kb[_K_I] = i_k
                    kb[_K_T] = t_k
                    kb[_K_ST] = s_k
                return int(from_q(c, qf if qf < base else base))
        q_new = int(newton(c, qf, q_k, rp_ohm))
        if q_new != qf:
            st = int(from_q(c, q_new))
            if (st & _ST_T_MAX) == ceiling:
                n = kb[_K_FJ]  # (c.fast_jumps)
                if n < _SAT30:  # a counter must never become a long int
                    kb[_K_FJ] = n + 1
                return st
            kb[_K_I] = i_k
            kb[_K_T] = t_k
            kb[_K_ST] = s_k
    st = int(from_q(c, qf))
    i = kb[_K_I]
    if st == _ST_T_MAX and ceiling == 0 and i < i_k:
        # entering the ceiling from the mE curve at a lower current I: Rp will rise
        # at least by the least elasticity, Rp (1 + e (I_k - I) / I); one more step
        # of the law on that Rp (I < 2**10: the divisor scaled into muldiv's range)
        if i < 1024:
            dr = int(muldiv(rp_ohm, i_k - i, i << 8, 8, _MQ_CAP))
        else:
            dr = int(muldiv(rp_ohm, i_k - i, i, 0, _MQ_CAP))
        rp2 = rp_ohm + (dr >> 12) * FAST_ELASTICITY_Q12 + (((dr & 0xFFF) * FAST_ELASTICITY_Q12) >> 12)  # least_elastic
        if rp2 <= _RP_MAX_OHM:
            kb[_K_I] = i_k
            kb[_K_T] = t_k
            kb[_K_ST] = s_k
            st = int(from_q(c, int(line(c, rp2))))
    elif (st & _ST_T_MAX) != 0 and ceiling == 0 and i > i_k and qf > (q_k << 4):
        # entering the ceiling from the mE curve at a higher current I: ceiling_bound's Newton
        # step, not the paper's step (that passed the fixed point: up to +38 % felt, an untrusted
        # model; the I_k floor: review of session 18)
        lq = qf >> 4
        q_new = int(ceiling_bound(ka, q_k, rp_ohm, lq, i_k))
        if q_new > lq:  # (only by the I_k floor)
            q_new = lq
        kb[_K_I] = i_k
        kb[_K_T] = t_k
        kb[_K_ST] = s_k
        st = int(from_q(c, q_new << 4))
    return st


@micropython.viper
def ceiling_bound(k, q_k: int, rp_ohm: int, lq: int, i_k: int) -> int:
    """The charge (pC) of a step from the pulse just measured (q_k, Rp = rp_ohm, current i_k)
    into the duration ceiling at a higher current, towards the law's charge lq (pC): Rp falls at
    most as 1/I there (beta < 1; a longer T only raises Rp), so L(Rp(Q)) >= h(Q) = L(Rp_k Q_k / Q),
    convex and falling, steepest at Q_k: G = -mQ Rp_k / Q_k, and the Newton step on h from Q_k,
    Q_k + (lq - Q_k) / (1 + |G|), stays below the loop's fixed point; at least I_k at t_max (below
    I_k, Rp would rise instead). k: the controller's int array c._k (mQ, t_max). Used by
    fast_pulse and by the skin model's unchecked refit (skin_model.SkinModel.jump)."""
    kb = ptr32(k)
    x = int(muldiv(kb[_K_MQN], rp_ohm, kb[_K_MQD], 0, _MQ_CAP))  # mQ Rp (pC)
    g = 8192 if x >= q_k << 1 else int(frac12(x, q_k))  # |G| in Q.12, at most 2
    q = q_k + (int(muldiv(lq - q_k, 4096, 4096 + g, 0, _MQ_CAP)) if lq > q_k else 0)
    q_lo = i_k * kb[_K_TMAX]
    return q_lo if q < q_lo else q


@micropython.viper
def newton(c, qf: int, q_k: int, rp_ohm: int) -> int:
    """A Newton step towards the self-consistent charge (1/16 pC), or qf.

    With the skin's response to charge along the mE curve linearised, slope
    s = dRp/dQ, the fixed point of Q = L(Rp(Q)) is Q* = (L(Rp_k) - G Q_k) / (1 - G),
    G = mQ s. G comes from the last two pulses (a secant) when they are a
    trustworthy pair, else from the skin's least elasticity (FAST_ELASTICITY_Q12,
    a lower bound on G: the step then never passes the fixed point of a skin
    that follows the model). docs/controller.md gives the rules; the paper's
    step L(Rp_k) (= qf) is returned whenever neither applies. (viper: mQ and q_max
    from c._k.)
    """
    if q_k <= 0:
        return qf
    k = ptr32(c._k)
    g = _NO_G
    up = 1  # a jump that raises the charge: at most 2 paper steps (secant)
    qb = 0  # the pulse before (c.before; read when the secant uses it)
    rb = 0
    if k[_K_B + _B_CLEAN] != 0:
        qb = k[_K_B + _B_Q]
        dq = q_k - qb
        adq = dq if dq >= 0 else 0 - dq
        if adq >= 64 and adq >= (q_k >> 5):  # enough excitation for a secant
            rb = k[_K_B + _B_RP]
            dr = rp_ohm - rb
            x = int(muldiv(k[_K_MQN], dr if dr >= 0 else 0 - dr, k[_K_MQD], 0, _MQ_CAP))  # mQ |dRp| (pC)
            if x < adq << 1:  # else |G| >= 2: the linear model is not trustworthy
                g = int(frac12(x, adq))  # |G| in Q.12
                if (dr < 0 and dq >= 0) or (dr >= 0 and dq < 0):
                    g = 0 - g
                if g > 3891 or g < -6144:  # G outside [-1.5, 0.95]: no stable fixed point nearby
                    g = _NO_G
    if g == _NO_G:  # the prior: |G| >= elasticity * mQ Rp / Q
        s = k[_K_ST]  # (c.status)
        ceiling = 1 if s == _ST_T_MAX else 0  # the pulse just measured was held at t_max
        if s != _ST_OK and ceiling == 0:  # another bound: no model of that path
            return qf
        x = int(muldiv(k[_K_MQN], rp_ohm, k[_K_MQD], 0, _MQ_CAP))  # mQ Rp (pC)
        if x >= q_k << 1:
            return qf
        g = (int(frac12(x, q_k)) * FAST_ELASTICITY_Q12) >> 12
        if ceiling:  # T fixed, only I moves: Rp falls as the charge rises, G < 0
            g = 0 - g
        elif g > 3891:
            return qf
        up = 2  # the prior's step does not pass the fixed point: at most 4 paper steps
    if up == 1 and g > 0 and qf - (q_k << 4) < 0 - (q_k >> 1):
        # a step down by more than Q_k/32 on a secant: the skin's elasticity grows as the
        # charge falls, so the chord through the two pulses under-predicts the fall of Rp
        # below Q_k (a felt surge). G from the pair's arc elasticity at Q_k, stretched:
        # G = k e_arc mQ Rp_k / Q_k, e_arc = (dRp / (Rp_k + Rp_b)) / (dQ / (Q_k + Q_b))
        r = 0x21000 if qb >> 5 >= q_k else int(frac12(q_k + qb, q_k))  # (Q_k + Q_b) / Q_k, Q.12, <= 33
        x = (((g * r) >> 12) * int(frac12(rp_ohm, rp_ohm + rb))) >> 12
        x = (x * FAST_LOWER_STRETCH_Q3) >> 3
        if x > g:
            g = x if x < _G_LOWER_MAX else _G_LOWER_MAX
    lq = qf >> 4  # L(Rp_k) in pC
    gq = (q_k >> 12) * g + (((q_k & 0xFFF) * g) >> 12)  # G Q_k in pC
    n = lq - gq
    if n <= 0:  # Q* <= 0: a step down as far as the cap below allows, else the paper's
        if g <= 0 or qf >= q_k << 4:
            return qf
        q_new = 0
    else:
        den = 4096 - g  # (1 - G) in Q.12, in [205, 10240]
        h = n // den
        q_max = k[_K_QMAX]
        if h > q_max >> 12:  # Q* > q_max: no need to compute it (it would pass 2**30)
            q_new = (q_max << 4) + 1  # _from_q clamps and flags it
        else:
            q_new = (h << 12) + (((n - h * den) << 12) // den)  # Q* in pC, < q_max + 2**12
            if q_new > q_max:
                q_new = (q_max << 4) + 1
            else:
                q_new = q_new << 4
    base = q_k << 4
    step = qf - base  # the paper's step, 1/16 pC
    jump = q_new - base
    if step == 0 or (jump > 0 and step < 0) or (jump <= 0 and step > 0):
        return qf  # not the paper's direction: keep the paper's step
    if step > 0:  # more charge: at most 2 (secant) or 4 (prior) paper steps: overshoot is felt
        if step < 0x4000000 and jump > step << up:
            q_new = base + (step << up)
    else:  # less charge: at most 4 paper steps, and not below Q_k/4 unless the paper's step is
        lo = base >> 2
        if 0 - step < 0x8000000 and base + (step << 2) > lo:
            lo = base + (step << 2)
        if lo > qf:  # (never more charge than the paper's step)
            lo = qf
        if q_new < lo:
            q_new = lo
    if q_new <= 0:
        return qf
    return q_new
