"""skin_model: MODE_FAST's electrode model, solved in integers (docs/controller.md,
"MODE_FAST with a skin model").

  Rp(I, T) = Rs + R(I) (1 - exp(-T / (R(I) Cp))),  R(I) = S (I / 1 mA)**-beta

is the electrode of docs/simulation.md. Rs, beta and Cp are fitted on the host
(host/skin.py) and set with Controller.set_skin; S is re-anchored to every
measurement. Logarithms are log2 in Q.16 ("l" names: li = log2 I, lt = log2 T,
ls = log2 S, lc = log2 Cp, lq = log2 Q). Every intermediate is below 2**30 and
nothing is allocated after construction.
"""

from array import array

try:
    import micropython
    from micropython import const
except ImportError:  # CPython: the decorator does nothing, ptr32 indexes the array itself

    class micropython:  # noqa: N801 (stands in for the module's decorator)
        @staticmethod
        def viper(f):
            return f

        native = viper

    def const(x):
        return x

    def ptr32(a):
        return a


from fast_step import ceiling_bound
from fixmath import _EXP_TAB, _LOG_TAB, log2q, word
from skin_tau import anchor_tau

# fixmath's 2**x and log2 tables (k = 0..63) with their first and second differences, one
# array (one global lookup a _root call): _root's inline interpolations read the
# differences instead of computing them (the same integers)
_T_E1 = const(64)  # 2**x: _TAB[k], its differences at _T_E1 + k, _T_E2 + k
_T_E2 = const(128)
_T_G = const(192)  # log2: _TAB[_T_G + k], its differences at _T_G1 + k, _T_G2 + k (negated)
_T_G1 = const(256)
_T_G2 = const(320)
_TAB = array("i", [_EXP_TAB[k] for k in range(64)])
for _t in (_EXP_TAB, _LOG_TAB):
    if _t is _LOG_TAB:
        _TAB.extend(array("i", [_t[k] for k in range(64)]))
    _TAB.extend(array("i", [_t[k + 1] - _t[k] for k in range(64)]))
    # (log2's second differences are negative: kept negated, as a 64-bit viper reads ptr32 words unsigned)
    _TAB.extend(array("i", [(_t[k + 2] - _t[k + 1] - _t[k + 1] + _t[k]) * (1 if _t is _EXP_TAB else -1) for k in range(64)]))
del _t

# the accepted ranges (Controller.set_skin)
SKIN_RS_MAX_OHM = const(5000)
SKIN_BETA_MIN_Q16 = const(6554)  # 0.1
SKIN_BETA_MAX_Q16 = const(98303)  # < 1.5
SKIN_CP_MIN_PF = const(100)
SKIN_CP_MAX_PF = const(2000000)  # 2 uF
# a jump on the skin model raises the charge by at most 2**this paper steps
FAST_MODEL_RAISE_LOG2 = const(4)
# a fresh rise into the duration ceiling whose predicted Rp rise exceeds Rp / 2**this is halved
FAST_MODEL_RP_RISE_LOG2 = const(3)
# a fall the law on the model (rule 2) asks for past Q_k/4 is searched on down to Q_k / 2**this when it
# asks at Q_k for less than half (skin_model._law_fall), or for any fall on the reading after one on which the
# paper's step asked for less than half and the model gave no answer: gel on a pulse at the duration ceiling
# asks for Q_k/5 ... Q_k/9 (before, the model-free step there: the first corrected pulse felt +45 ... +131 %,
# issue 13's study; sessions 27-28)
FAST_MODEL_FALL_LOG2 = const(4)
_L_FALL_ASK = const(0x10000)  # log2 of that half (Q.16): 1 octave
# a reading that misses a checked model's prediction by more than Rp / 2**this, with no refit
# taken to explain it, is a step of the skin: the next jump is a fresh one (rules 3 and 6)
FAST_MODEL_STEP_LOG2 = const(3)
# ... and so is such a miss whose two-pulse refit puts Cp above the fitted one by more than this
# (log2 Q.16: 1/64 octave, the rounding of the reads): the skin's Cp is c x contact area, a peel
# lowers it and hydration leaves it, so such a refit is a pair of readings across a step (a peel
# right after another step): it is refused, Cp kept (review of session 17; docs/controller.md,
# rule 3). The same bound holds for the refit on a pulse marked as a step (rule 4)
FAST_MODEL_CP_ABOVE = const(0x400)
_L_STEP = const(0x2B80)  # log2(1 + 1/8) in Q.16
# rule 7's tau gain: log2 (tau the monitor reads / the skin's R(I) Cp), measured by the host on the calibration
# sweeps the model is fitted to (host/skin.py: tau_gain) and sent with it (Controller.set_skin); past it, or none
# sent, tau is not used (docs/controller.md, rule 7)
SKIN_TAU_MAX_Q16 = const(0x7FFF)  # |gain| just under 1/2 octave (Q.16): SET_SKIN carries it as a u16 + 0x8000
SKIN_TAU_OFF = const(-0x8000)  # "no tau gain": rule 7 does not read tau (0 on the wire)
# rule 7 anchors on a tau only when the Cp it gives agrees within this (log2 Q.16: 1/8 octave) with the Cp the
# tau read before it gave: a single wild tau (or Rp) never shapes the model (review of session 26: tau x 0.5 on one
# pulse, +16 % felt)
FAST_TAU_AGREE = const(0x2000)
# ... and only after the calibration pulse's tau (told before calibrate) gave the fitted Cp within FAST_TAU_CAL_AGREE
# (1/16 octave; a true tau: within +-0.02 on 13 of 15 study electrodes, a gain x 1.15 moves it 0.08-0.15): a gain
# that is not the monitor's now (a stale sweeps file, a monitor changed since) turns tau off for that calibration,
# never on (review of session 26: a gain x 1.15 after the sweeps +8 %, x 1.25 +13 % felt)
FAST_TAU_CAL_AGREE = const(0x1000)
# ... and not after FAST_TAU_STRIKES more tau reads disagreed than agreed since the calibration: a decay read much
# noisier than on the sweeps (review of session 26: 0.2 octave of noise in the run only, +26 % felt) turns tau off
# until the next calibration (a step of the skin is one disagreement, then its reads agree)
FAST_TAU_STRIKES = const(3)
_L_MOVED = const(0x800)  # 1/32 octave (Q.16): a pulse that moved I by less does not check a refitted Cp
_L_REFIT = const(0x2000)  # 1/8 octave (Q.16): a pulse that moved I by more may refit Cp (rule 4). The pair's
# reads differ by 1-2 % on the realistic board between pulses of different T: on a move of 1/32 ... 1/8 that is
# the refit's whole answer (review 2 of session 28: Cp 1.475 octave low on a move of 2.8 %, and a wild read
# after it felt +49 %, twice)
# the model's work per pulse (bounds Controller.update on the chip): a jump's root searches
# may spend FAST_MODEL_WORK_MAX units, one per evaluation of the model and _ROOT_WORK per
# search (its set-up costs about that many evaluations on the chip); a jump that runs out
# takes the paper's step (fast_step.fast_pulse)
FAST_MODEL_WORK_MAX = const(80)
_ROOT_WORK = const(4)

# sensation_core's RP_MAX_OHM and counter ceiling: a const() is folded only inside its own
# module, and importing the core's would be a dictionary lookup per use on the chip (and a
# circular import); tests/test_core_split.py checks that the values agree.
_RP_MAX_OHM = const(200000)
_SAT30 = const(0x3FFFFFFF)
_MQ_CAP = const(0x1FFFFFFF)
_ST_T_MAX = const(0x008)  # sensation_core.ST_T_MAX
_KB_I = const(17)  # the words of the controller's c._k that hold c.before (fast_step._K_B):
_KB_T = const(18)  # its I, T and Rp
_KB_RP = const(20)
_KC_I = const(22)  # and the next pulse: c.i_ua, c.t_us, c.status (sensation_core._K_I, _K_T, _K_ST)
_KC_T = const(23)
_KC_ST = const(24)
_KC_MJ = const(29)  # c.model_jumps
_KC_LT = const(34)  # log2 tau told before calibrate: the calibration pulse's (sensation_core._K_LT)
_KC_LTU = const(35)  # log2 tau of the pulse just measured, Q.16, 0: none (sensation_core._K_LTU)

_L_1E6 = const(1306235)  # log2(1e6): tau_us = R_ohm * Cp_pF / 1e6
_L_E = const(94548)  # log2(e)
_L_1MA = const(653118)  # log2(1000 uA): the model's reference current
_L_Z12 = const(234946)  # log2(12): beyond it exp(-T/tau) < 2**-17, taken as 0
_L_R_MAX = const(1310720)  # 20.0: R(I) above 2**20 ohm is far beyond RP_MAX_OHM
_L_LN2 = const(-34653)  # log2(ln 2)
NOROOT = const(-0x3FFFFFFF)  # "no sign change": what _root and _law_q return then
_FB_KNOWN = const(0x1000000)  # in _root's kind: g(b) is v[_V_FB] - _V_BIAS (evaluated, nothing changed since)
_FA_KNOWN = const(0x2000000)  # in _root's kind: g(a) is v[_V_FB] - _V_BIAS (as _FB_KNOWN)
_RAW_IT = const(0x4000000)  # in _root's kind: pulse p's _P_LI, _P_LT words hold I (uA) and T (us), their log2 first

# what _root's g(kind, x, lc) measures, x being the unknown (p, o: the pulses it reads)
_K_ANCHOR = const(0)  # x = log2 S: the model (log2 Cp = lc) reads pulse p's Rp
_K_PEEL = const(1)  # x = log2 contact change since pulse o: the model reads pulse p's Rp
_K_LAW = const(2)  # x = log2 Q on the mE curve: the law L(Rp(Q)) - Q
_K_CEIL = const(3)  # x = log2 I at T = t_max: the line L(Rp) - I t_max
_K_TWO = const(4)  # x = log2 R(I) at pulse p, Cp from p's Rp: the model reads pulse o's Rp
_K_RP = const(5)  # not a root: the model's Rp itself for x = log2 S at pulse p (SkinModel.rp)
# (g compares logarithms: log2 of the model's Rp or charge less log2 of the one it must
# equal, nearly linear in x, so the regula falsi needs few evaluations)

# SkinModel.v (an array('i')): everything _root reads, so that a search is one call with no
# attribute lookup (the chip pays ~10 us per call and per lookup; this is why the pulses the
# model reads live here, not in objects). Values never negative: a 64-bit viper reads a ptr32
# word unsigned, so log2 S and log2 Cp are kept + _V_BIAS.
_V_RS = const(0)  # the fitted parameters: Rs (ohm), beta (Q.16)
_V_BETA = const(1)
_V_LS = const(2)  # the model's log2 S and log2 Cp now (SkinModel.ls, .lc), + _V_BIAS
_V_LC = const(3)
_V_LME = const(4)  # the law (SkinModel.law, .limits): log2 mE, log2 t_max,
_V_LTMAX = const(5)
_V_YQ4 = const(6)  # and the controller's Eq. 3: y* (1/16 pC), mQ's numerator (pC),
_V_MQN = const(7)  # -x* (ohm), mQ's denominator (ohm), q_max - y* (1/16 pC)
_V_XS = const(8)
_V_MQD = const(9)
_V_LCAP = const(10)
_V_LCTWO = const(11)  # log2 Cp found by the last _K_TWO evaluation, + _V_BIAS
_V_WORK = const(12)  # work units spent since the jump began (SkinModel.jump)
_V_CUT = const(13)  # 1: a root search of this jump ran out of FAST_MODEL_WORK_MAX
_V_LQK = const(14)  # log2 of the charge of the pulse just measured (pC)
_V_LQMAX = const(30)  # the limits (SkinModel.limits): log2 q_max, log2 i_min, log2 i_max
_V_LIMIN = const(31)
_V_LIMAX = const(32)
# three pulses of _P_N words each: the pulse just measured, the one before it, and the
# pulse SkinModel.rp reads; _root is told which two it reads (p, o) in its kind argument
_V_NOW = const(15)
_V_BEFORE = const(20)
_V_PROBE = const(25)
_P_LI = const(0)  # log2 I (uA), Q.16
_P_LT = const(1)  # log2 T (us), Q.16
_P_RP = const(2)  # the Rp measured on it (ohm)
_P_RLP = const(3)  # log2 of that Rp
_P_LS = const(4)  # log2 S with which the model reads it (set for the pulse before), + _V_BIAS
_V_ON = const(33)  # SkinModel.on, .jumped, .predicted_rp_ohm (properties: the words)
_V_JUMPED = const(34)
_V_PRED = const(35)
_V_FB = const(36)  # g at the search's upper end, + _V_BIAS, when the caller knows it (_FB_KNOWN)
# the pulse in _V_NOW as given (its I, T; its Rp is _V_NOW + _P_RP) and what its anchor found
# (log2 S + _V_BIAS, for log2 Cp + _V_BIAS, at this many work units; _V_ACH_OK 0: none yet):
# the next jump's pulse before is this one, and its words and its anchor are taken from here
# instead of being computed again when nothing they depend on has changed (bit-identical,
# the units charged as if the search had run: SkinModel.jump)
_V_NI = const(37)
_V_NT = const(38)
_V_ACH_OK = const(39)
_V_ACH_LS = const(40)
_V_ACH_LC = const(41)
_V_ACH_W = const(42)
_V_SNA = const(43)  # 1: the last jump saw a step of the skin on its pulse and gave no answer;
_V_SNA_I = const(44)  # that pulse's I and T
_V_SNA_T = const(45)
_V_RFT = const(46)  # 1: the last jump's Cp came from a two-pulse refit taken on its pulse
_V_TJ = const(47)  # SkinModel.tau_jumps: jumps anchored on the decay's tau (rule 7)
_V_TCK = const(48)  # SkinModel.tau_ok: 1: rule 7 reads tau (the host measured its gain, _V_TLK), 0: not
_V_TLC = const(49)  # 1: the model's Cp (_V_LC) is a tau anchor's (a jump without tau takes the fitted Cp back)
_V_TLK = const(50)  # SkinModel.tau_gain_q16 + _V_BIAS: log2 (tau read / the skin's tau), Q.16, as set
_V_TPC = const(51)  # log2 Cp (+ _V_BIAS) the last tau read gave (its anchor), 0: none since the calibration
_V_TCHK = const(52)  # SkinModel.tau_checked: 1 the calibration pulse's tau agreed with the fitted model (rule 7 on
# until the next calibration), 0 not (tau not used)
_V_TSTR = const(53)  # tau reads that disagreed with the one before, less those that agreed (>= 0)
_V_BFA = const(54)  # 1: the last jump's paper's step asked for less than half of Q_k and it gave no answer;
_V_BFA_I = const(55)  # that pulse's I and T (on the next reading from it, _law_fall's ask is any fall)
_V_BFA_T = const(56)
_V_N = const(57)
_V_BIAS = const(0x10000000)


@micropython.viper
def _root(vv, kind: int, a: int, b: int, lc0: int) -> int:
    """x in [a, b] where g(kind, x, lc0) changes sign (Illinois' regula falsi), to 1/2**16,
    on the values in vv (SkinModel.v); NOROOT if the ends have one sign or g fails. With
    b < a: g(kind, a, lc0) itself. kind = _K_* + (p << 8) + (o << 16) (+ _FB_KNOWN), p and o the
    pulses read (_V_NOW, _V_BEFORE, _V_PROBE). _K_ANCHOR finds its own range from pulse
    p, R(I) >= Rp - Rs up to 16 times more (a, b are not read).
    One machine-code function (viper) with the model's Rp and fixmath.exp2q's
    interpolation inline: no call per evaluation. Every value is below 2**30, so
    32-bit (ARM) and 64-bit words give Python's results; the interpolation
    floor(num * w / den) is one division where w < 2**12 (num * w < 2**30), else it goes in two
    9-bit halves of w (num <= den < 2**18, w <= 2**18)."""
    v = ptr32(vv)
    e = ptr32(_TAB)  # 2**x and log2 tables, their differences
    beta = v[_V_BETA]
    rs = v[_V_RS]
    pb = (kind >> 8) & 0xFF
    ob = (kind >> 16) & 0xFF
    fbk = (kind >> 24) & 1  # _FB_KNOWN
    fak = (kind >> 25) & 1  # _FA_KNOWN
    if (kind >> 26) & 1:  # _RAW_IT: log2 of pulse p's I and T in place (fixmath.log2q, inline; as SkinModel.jump's)
        j = 0
        while j < 2:
            n = v[pb + j]  # (_P_LI, _P_LT)
            if n < 1:
                n = 1
            k = 22
            if n >= 0x800000:  # to [2**22, 2**23): a binary search (a shift loop is ~0.6 us a bit on the chip)
                if n >= 0x4000000:
                    n >>= 4
                    k += 4
                if n >= 0x1000000:
                    n >>= 2
                    k += 2
                if n >= 0x800000:
                    n >>= 1
                    k += 1
            else:
                if n < 0x80:
                    n <<= 16
                    k -= 16
                if n < 0x8000:
                    n <<= 8
                    k -= 8
                if n < 0x80000:
                    n <<= 4
                    k -= 4
                if n < 0x200000:
                    n <<= 2
                    k -= 2
                if n < 0x400000:
                    n <<= 1
                    k -= 1
            eu = (n >> 16) - 64
            m = n & 0xFFFF
            w = m >> 8
            v[pb + j] = (k << 16) + e[_T_G + eu] + ((e[_T_G1 + eu] * m + 0x8000) >> 16) + ((w * (256 - w) * e[_T_G2 + eu] + 0x10000) >> 17)
            j += 1
    kind = kind & 0xFF
    if kind == _K_ANCHOR:  # R(I) >= Rp - Rs: S is searched from there up to 16 times more
        n = v[pb + _P_RP] - rs  # lo = log2q(n) + mul_q16(log2 I - log2 1 mA, beta), inline
        if n < 16:
            return NOROOT
        k = 22
        if n >= 0x800000:  # to [2**22, 2**23): a binary search (a shift loop is ~0.6 us a bit on the chip)
            if n >= 0x4000000:
                n >>= 4
                k += 4
            if n >= 0x1000000:
                n >>= 2
                k += 2
            if n >= 0x800000:
                n >>= 1
                k += 1
        else:
            if n < 0x80:
                n <<= 16
                k -= 16
            if n < 0x8000:
                n <<= 8
                k -= 8
            if n < 0x80000:
                n <<= 4
                k -= 4
            if n < 0x200000:
                n <<= 2
                k -= 2
            if n < 0x400000:
                n <<= 1
                k -= 1
        eu = (n >> 16) - 64
        m = n & 0xFFFF
        w = m >> 8
        a = (k << 16) + e[_T_G + eu] + ((e[_T_G1 + eu] * m + 0x8000) >> 16) + ((w * (256 - w) * e[_T_G2 + eu] + 0x10000) >> 17)
        ma = v[pb + _P_LI] - _L_1MA
        mc = 0 - ma if ma < 0 else ma
        my = (((mc >> 10) * beta) >> 6) + (((mc & 0x3FF) * beta) >> 16)
        a += 0 - my if ma < 0 else my
        b = a + 0x40000
    # one search's set-up of the model's evaluation: what x does not change, read and
    # computed once (bit for bit the sums and products the evaluation made each time).
    # An evaluation gets lr = log2 R(I) and lq = log2 (T / Cp) + log2 1e6 from x and these:
    # hmy = mul_q16(log2 I - log2 1 mA, beta) where I is fixed, hls / hq the parts of log2 S
    # and of lq that x does not move, hrl the log2 Rp read (_K_ANCHOR, _K_PEEL, _K_TWO),
    # and for _K_LAW, _K_CEIL Eq. 3's words (mQ's numerator in three 11-bit parts, its
    # denominator, -x*, the cap and the cap's three shifts).
    hmy = 0
    hls = 0
    hq = 0
    hrl = 0
    hli = 0
    hmb = 0
    hsg = 0
    hmc = 1
    hxs = 0
    hm1 = 0
    hm2 = 0
    hm3 = 0
    hcap = 0
    hc26 = 0
    hc15 = 0
    hc4 = 0
    hg = 0
    hyq = 0
    h2m = 0
    h2t = 0
    h2r = 0
    hk = kind  # the evaluation's branch (_K_RP takes _K_ANCHOR's)
    hf = 1  # what g is: 1 log2 of the model's Rp less the one read, 2 log2 of Eq. 3's charge less x's, 0 the Rp itself
    if kind == _K_LAW or kind == _K_CEIL:
        hf = 2
        hls = v[_V_LS] - _V_BIAS
        if kind == _K_LAW:  # li = log2 mE - x, lt = 2 x - log2 mE
            hli = v[_V_LME]
            hq = _L_1E6 - hli - (v[_V_LC] - _V_BIAS)
            hli -= _L_1MA
            hrl = 0x40000
        else:  # li = x, lt = log2 t_max
            hli = _L_1MA
            hq = v[_V_LTMAX] - (v[_V_LC] - _V_BIAS) + _L_1E6
            hrl = v[_V_LTMAX] + 0x40000
        hyq = v[_V_YQ4]
        hm1 = v[_V_MQN]
        hm2 = (hm1 >> 11) & 0x7FF
        hm3 = hm1 & 0x7FF
        hm1 = hm1 >> 22
        hxs = v[_V_XS]
        hmc = v[_V_MQD]
        hcap = v[_V_LCAP]
        hc26 = hcap >> 26
        hc15 = hcap >> 15
        hc4 = hcap >> 4
        hg = 1 if hm1 != 0 or hc26 < 0 else 0
    else:
        n = ob if kind == _K_TWO else pb  # the pulse whose I and T the model reads
        ma = v[n + _P_LI] - _L_1MA  # mul_q16(ma, beta), inline (beta >= 0)
        mc = 0 - ma if ma < 0 else ma
        my = (((mc >> 10) * beta) >> 6) + (((mc & 0x3FF) * beta) >> 16)
        hmy = 0 - my if ma < 0 else my
        hrl = v[n + _P_RLP]
        if kind == _K_PEEL:  # ls = log2 S of pulse o + mul_q16(x, beta - 1), lc = log2 Cp + x
            hls = v[ob + _P_LS] - _V_BIAS
            hq = v[pb + _P_LT] - (v[_V_LC] - _V_BIAS) + _L_1E6
            hmb = beta - 0x10000
            hsg = 1 if hmb < 0 else 0
            if hmb < 0:
                hmb = 0 - hmb
        elif kind == _K_TWO:  # lc and ls from pulse p's reading
            hq = v[ob + _P_LT] + _L_1E6
            ma = v[pb + _P_LI] - _L_1MA  # mul_q16(ma, beta), inline (beta >= 0)
            mc = 0 - ma if ma < 0 else ma
            my = (((mc >> 10) * beta) >> 6) + (((mc & 0x3FF) * beta) >> 16)
            h2m = 0 - my if ma < 0 else my
            h2t = v[pb + _P_LT] + _L_1E6 + 0x100000 - _L_LN2
            h2r = rs - v[pb + _P_RP]
        else:  # _K_ANCHOR, _K_RP: ls = x, lc = lc0
            hq = v[pb + _P_LT] - lc0 + _L_1E6
            if kind == _K_RP:
                hk = _K_ANCHOR
                hf = 0
    only = 1 if b < a else 0
    x0 = lc0 if kind == _K_LAW else NOROOT  # _K_LAW: lc0 is a guess of the root (else none)
    if not only:
        v[_V_WORK] += _ROOT_WORK
    phase = 0  # 0: evaluating at a, 1: at b, 2: inside
    fa = 0
    fb = 0
    side = 0
    it = 0  # interpolation steps
    x = a
    if fak and not only:  # g(a) known: its unit of work and its budget check, as if evaluated
        if v[_V_WORK] >= FAST_MODEL_WORK_MAX:
            v[_V_CUT] = 1
            return NOROOT
        v[_V_WORK] += 1
        fa = v[_V_FB] - _V_BIAS
        x = b
        phase = 1
    while True:
        if not only:  # the jump's budget
            if v[_V_WORK] >= FAST_MODEL_WORK_MAX:
                v[_V_CUT] = 1
                return NOROOT
            v[_V_WORK] += 1
        ok = 1
        if hk == _K_LAW:  # x = log2 Q (1/16 pC ... see below) on the mE curve
            ma = hli - x  # lr = log2 R(I) = ls - mul_q16(li - log2 1 mA, beta), inline (beta >= 0; hli: log2 mE - log2 1 mA)
            if ma < 0:
                ma = 0 - ma
                lr = hls + (((ma >> 10) * beta) >> 6) + (((ma & 0x3FF) * beta) >> 16)
            else:
                lr = hls - ((((ma >> 10) * beta) >> 6) + (((ma & 0x3FF) * beta) >> 16))
            lq = (x << 1) + hq  # log2 (T / Cp) + log2 1e6
        elif hk == _K_ANCHOR:  # (and _K_RP) x = log2 S, lc = lc0
            lr = x - hmy
            lq = hq
        elif hk == _K_CEIL:  # x = log2 I at t_max
            ma = x - hli  # lr as _K_LAW's (hli: log2 1 mA)
            if ma < 0:
                ma = 0 - ma
                lr = hls + (((ma >> 10) * beta) >> 6) + (((ma & 0x3FF) * beta) >> 16)
            else:
                lr = hls - ((((ma >> 10) * beta) >> 6) + (((ma & 0x3FF) * beta) >> 16))
            lq = hq
        elif hk == _K_PEEL:  # contact a: S ~ a**(beta - 1), Cp ~ a, from pulse o's S
            if x < 0:  # my = mul_q16(x, beta - 1), inline (hmb: |beta - 1|, hsg: 1 if beta < 1)
                ma = 0 - x
                my = (((ma >> 10) * hmb) >> 6) + (((ma & 0x3FF) * hmb) >> 16)
                if hsg == 0:
                    my = 0 - my
            else:
                my = (((x >> 10) * hmb) >> 6) + (((x & 0x3FF) * hmb) >> 16)
                if hsg != 0:
                    my = 0 - my
            lr = hls + my - hmy
            lq = hq - x
        else:  # _K_TWO: p's reading gives Cp in closed form, Cp = T / (R z), z = -ln(1 - (Rp - Rs) / R)
            n = x  # r = exp2q(n), inline
            k = (n >> 10) & 0x3F
            eu = n & 0x3FF
            n = n >> 16
            w = eu >> 2
            m = e[k] + ((e[_T_E1 + k] * eu + 512) >> 10) + ((w * (w - 256) * e[_T_E2 + k] + 0x10000) >> 17)
            if n >= 22:
                r = m << (n - 22)
            elif n < -2:
                r = 0
            else:
                r = (m + (1 << (21 - n))) >> (22 - n)
            n = r + h2r  # my = log2q(n), inline (h2r = Rs - Rp)
            if n < 1:
                n = 1
            k = 22
            if n >= 0x800000:  # to [2**22, 2**23): a binary search (a shift loop is ~0.6 us a bit on the chip)
                if n >= 0x4000000:
                    n >>= 4
                    k += 4
                if n >= 0x1000000:
                    n >>= 2
                    k += 2
                if n >= 0x800000:
                    n >>= 1
                    k += 1
            else:
                if n < 0x80:
                    n <<= 16
                    k -= 16
                if n < 0x8000:
                    n <<= 8
                    k -= 8
                if n < 0x80000:
                    n <<= 4
                    k -= 4
                if n < 0x200000:
                    n <<= 2
                    k -= 2
                if n < 0x400000:
                    n <<= 1
                    k -= 1
            eu = (n >> 16) - 64
            m = n & 0xFFFF
            w = m >> 8
            my = (k << 16) + e[_T_G + eu] + ((e[_T_G1 + eu] * m + 0x8000) >> 16) + ((w * (256 - w) * e[_T_G2 + eu] + 0x10000) >> 17)
            my = x - my  # log2 (R / (R - Rp + Rs)) = z / ln 2
            if my <= 0:
                ok = 0
            else:
                n = my  # lc = log2q(n), inline
                if n < 1:
                    n = 1
                k = 22
                if n >= 0x800000:  # to [2**22, 2**23): a binary search (a shift loop is ~0.6 us a bit on the chip)
                    if n >= 0x4000000:
                        n >>= 4
                        k += 4
                    if n >= 0x1000000:
                        n >>= 2
                        k += 2
                    if n >= 0x800000:
                        n >>= 1
                        k += 1
                else:
                    if n < 0x80:
                        n <<= 16
                        k -= 16
                    if n < 0x8000:
                        n <<= 8
                        k -= 8
                    if n < 0x80000:
                        n <<= 4
                        k -= 4
                    if n < 0x200000:
                        n <<= 2
                        k -= 2
                    if n < 0x400000:
                        n <<= 1
                        k -= 1
                eu = (n >> 16) - 64
                m = n & 0xFFFF
                w = m >> 8
                lc = (k << 16) + e[_T_G + eu] + ((e[_T_G1 + eu] * m + 0x8000) >> 16) + ((w * (256 - w) * e[_T_G2 + eu] + 0x10000) >> 17)
                lc = h2t - x - lc  # log2 T_p - x + log2 1e6 - (lc - 16 + log2 ln 2)
                v[_V_LCTWO] = lc + _V_BIAS
                lr = x + h2m - hmy  # ls = x + mul_q16(log2 I_p - log2 1 mA, beta)
                lq = hq - lc
        fx = NOROOT
        if ok:
            # the model's Rp (SkinModel.rp) for lr = log2 R(I), lq = log2 (T / Cp) + log2 1e6
            lz = lq - lr  # log2 (T / tau), tau = R Cp
            if lz < -0x10000:  # z < 1/2: R (1 - e^-z) = (T / Cp) (1 - e^-z) / z, by its series
                if lq > _L_R_MAX:  # lq = log2 (R z) = log2 (T / Cp), ohm
                    rp = 0x200000
                else:
                    z = 0
                    if lz > -0x1E0000:  # z in Q.14, < 2**13
                        n = lz + 0xE0000  # z = exp2q(n), inline
                        k = (n >> 10) & 0x3F
                        eu = n & 0x3FF
                        n = 22 - (n >> 16)  # the right shift
                        w = eu >> 2
                        m = e[k] + ((e[_T_E1 + k] * eu + 512) >> 10) + ((w * (w - 256) * e[_T_E2 + k] + 0x10000) >> 17)
                        if n > 24:  # (2**x for x >= 13 not here: lz < -1)
                            z = 0
                        else:
                            z = (m + (1 << (n - 1))) >> n
                    # (1 - e^-z) / z in Q.14; z, u, (z * u) >> 14 in [0, 2**13]: // 5 and // 3 are
                    # exact as * 52429 >> 18 and * 43691 >> 17 there (tests/test_skin_eval.py), // 4, // 2 shifts
                    u = 16384 - ((z * 52429) >> 18)
                    u = 16384 - (((z * u) >> 14) >> 2)
                    u = 16384 - ((((z * u) >> 14) * 43691) >> 17)
                    u = 16384 - (((z * u) >> 14) >> 1)
                    n = lq  # r = exp2q(n), inline
                    k = (n >> 10) & 0x3F
                    eu = n & 0x3FF
                    n = 22 - (n >> 16)  # the right shift
                    w = eu >> 2
                    m = e[k] + ((e[_T_E1 + k] * eu + 512) >> 10) + ((w * (w - 256) * e[_T_E2 + k] + 0x10000) >> 17)
                    if n > 24:  # (2**x for x > 20 not here: lq <= _L_R_MAX)
                        r = 0
                    else:
                        r = (m + (1 << (n - 1))) >> n
                    rp = rs + (((r >> 10) * u + (((r & 0x3FF) * u) >> 10) + 8) >> 4)  # rounded
            elif lr > _L_R_MAX:
                rp = 0x200000
            else:
                if lz > _L_Z12:  # charged: exp(-z) < 2**-17
                    u = 0x8000
                else:
                    n = lz + 0x100000  # z = exp2q(n), inline
                    k = (n >> 10) & 0x3F
                    eu = n & 0x3FF
                    n = 22 - (n >> 16)  # the right shift
                    w = eu >> 2
                    m = e[k] + ((e[_T_E1 + k] * eu + 512) >> 10) + ((w * (w - 256) * e[_T_E2 + k] + 0x10000) >> 17)
                    z = (m + (1 << (n - 1))) >> n  # (n in [3, 7] here: lz in [-1, _L_Z12])
                    n = 0xF0000 - ((((z >> 8) * _L_E) >> 8) + (((z & 0xFF) * _L_E) >> 16))  # u = exp2q(n), inline: log2 e^-z + 15
                    k = (n >> 10) & 0x3F
                    eu = n & 0x3FF
                    n = 22 - (n >> 16)  # the right shift
                    w = eu >> 2
                    m = e[k] + ((e[_T_E1 + k] * eu + 512) >> 10) + ((w * (w - 256) * e[_T_E2 + k] + 0x10000) >> 17)
                    if n > 24:  # (2**x for x > 15 not here: log2 e^-z <= 0)
                        u = 0
                    else:
                        u = (m + (1 << (n - 1))) >> n
                    u = 0x8000 - u  # 1 - e^-z in Q.15
                n = lr  # r = exp2q(n), inline
                k = (n >> 10) & 0x3F
                eu = n & 0x3FF
                n = 22 - (n >> 16)  # the right shift
                w = eu >> 2
                m = e[k] + ((e[_T_E1 + k] * eu + 512) >> 10) + ((w * (w - 256) * e[_T_E2 + k] + 0x10000) >> 17)
                if n > 24:  # (2**x for x > 20 not here: lr <= _L_R_MAX)
                    r = 0
                else:
                    r = (m + (1 << (n - 1))) >> n
                if u == 0x8000:  # (the rounded product below is r itself then)
                    rp = rs + r
                else:
                    rp = rs + (((r >> 10) * u + (((r & 0x3FF) * u) >> 10) + 16) >> 5)  # rounded
            if hf == 2:  # _K_LAW, _K_CEIL: log2 of the line's charge L(Rp) less the pulse's (1/16 pC)
                if rp > _RP_MAX_OHM:
                    rp = _RP_MAX_OHM
                # Eq. 3 (the controller's _line): y* + muldiv(mQ num, Rp - x*, mQ den, 4, q_max - y*), inline
                # (a long division by 11-bit parts of mQ's numerator; its top part, 0 below 2**22, only if hg)
                mb = rp + hxs
                if hg:  # from the top part
                    my = hm1 * mb
                    dq = my // hmc
                    dr = my - dq * hmc
                    if dq > hc26:
                        dq = hcap + 1
                    else:
                        my = (dr << 11) + hm2 * mb
                        dd = my // hmc
                        dq = (dq << 11) + dd
                        dr = my - dd * hmc
                        if dq > hc15:
                            dq = hcap + 1
                        else:
                            my = (dr << 11) + hm3 * mb
                            dd = my // hmc
                            dq = (dq << 11) + dd
                            dr = my - dd * hmc
                            if dq > hc4:
                                dq = hcap + 1
                            else:
                                dq = (dq << 4) + (dr << 4) // hmc
                                if dq > hcap:
                                    dq = hcap + 1
                else:  # the same from the second part (the top part's quotient and remainder 0, not above hc26)
                    my = hm2 * mb
                    dq = my // hmc
                    dr = my - dq * hmc
                    if dq > hc15:
                        dq = hcap + 1
                    else:
                        my = (dr << 11) + hm3 * mb
                        dd = my // hmc
                        dq = (dq << 11) + dd
                        dr = my - dd * hmc
                        if dq > hc4:
                            dq = hcap + 1
                        else:
                            dq = (dq << 4) + (dr << 4) // hmc
                            if dq > hcap:
                                dq = hcap + 1
                n = hyq + dq  # my = log2q(n), inline (hyq: y*)
                if n < 1:
                    n = 1
                k = 22
                if n >= 0x800000:  # to [2**22, 2**23): a binary search (a shift loop is ~0.6 us a bit on the chip)
                    if n >= 0x4000000:
                        n >>= 4
                        k += 4
                    if n >= 0x1000000:
                        n >>= 2
                        k += 2
                    if n >= 0x800000:
                        n >>= 1
                        k += 1
                else:
                    if n < 0x80:
                        n <<= 16
                        k -= 16
                    if n < 0x8000:
                        n <<= 8
                        k -= 8
                    if n < 0x80000:
                        n <<= 4
                        k -= 4
                    if n < 0x200000:
                        n <<= 2
                        k -= 2
                    if n < 0x400000:
                        n <<= 1
                        k -= 1
                eu = (n >> 16) - 64
                m = n & 0xFFFF
                w = m >> 8
                my = (k << 16) + e[_T_G + eu] + ((e[_T_G1 + eu] * m + 0x8000) >> 16) + ((w * (256 - w) * e[_T_G2 + eu] + 0x10000) >> 17)
                fx = my - (x + hrl)  # hrl: 4 (1/16 pC), + log2 t_max for _K_CEIL
            elif hf == 1:  # _K_ANCHOR, _K_PEEL, _K_TWO: log2 of the model's Rp less the one read (hrl)
                n = rp  # my = log2q(n), inline
                if n < 1:
                    n = 1
                k = 22  # to [2**22, 2**23): a binary search (Rp < 2**23 here: r <= 2**20, Rs <= 5000)
                if n < 0x80:
                    n <<= 16
                    k -= 16
                if n < 0x8000:
                    n <<= 8
                    k -= 8
                if n < 0x80000:
                    n <<= 4
                    k -= 4
                if n < 0x200000:
                    n <<= 2
                    k -= 2
                if n < 0x400000:
                    n <<= 1
                    k -= 1
                eu = (n >> 16) - 64
                m = n & 0xFFFF
                w = m >> 8
                my = (k << 16) + e[_T_G + eu] + ((e[_T_G1 + eu] * m + 0x8000) >> 16) + ((w * (256 - w) * e[_T_G2 + eu] + 0x10000) >> 17)
                fx = my - hrl
            else:  # _K_RP
                fx = rp
        if only:
            return fx
        if phase == 0:
            fa = fx
            x = b
            phase = 1
            if fbk == 0:
                continue
            # g(b) known: its unit of work and its budget check, as if evaluated
            if v[_V_WORK] >= FAST_MODEL_WORK_MAX:
                v[_V_CUT] = 1
                return NOROOT
            v[_V_WORK] += 1
            fx = v[_V_FB] - _V_BIAS
        if phase == 1:
            fb = fx
            phase = 2
            if fa == NOROOT or fb == NOROOT or (fa > 0 and fb > 0) or (fa <= 0 and fb <= 0):
                if fa != 0 and fb != 0:
                    return NOROOT
                return a if fa == 0 else b
        else:
            if fx == NOROOT:
                return NOROOT
            if fx == 0:
                return x
            if (fx > 0 and fa > 0) or (fx <= 0 and fa <= 0):  # Illinois: halve the end kept twice running
                a = x
                fa = fx
                if side < 0:
                    fb = fb >> 1 if fb > 1 or fb < -1 else fb
                side = -1
            else:
                b = x
                fb = fx
                if side > 0:
                    fa = fa >> 1 if fa > 1 or fa < -1 else fa
                side = 1
        if b - a <= 1 or it >= 40:
            break
        it += 1
        w = b - a
        num = fa if fa > 0 else 0 - fa
        den = num + (fb if fb > 0 else 0 - fb)
        while den >= 0x40000:
            den >>= 1
            num >>= 1
        if den >= 256 and w <= 0x40000:
            if w < 0x1000:  # num * w < 2**30 (num <= den < 2**18): one division, the same floor
                x = a + (num * w) // den
            else:  # floor(num * w / den) in two 9-bit parts of w
                t = num * (w >> 9)
                q = t // den
                t = ((t - q * den) << 9) + num * (w & 0x1FF)
                x = a + (q << 9) + t // den
        else:
            x = a + (w >> 1)
        if x <= a:
            x = a + 1
        elif x >= b:
            x = b - 1
        if it == 1 and x0 > a and x0 < b:  # the caller's guess first
            x = x0
    if (fa if fa > 0 else 0 - fa) <= (fb if fb > 0 else 0 - fb):
        return a
    return b


@micropython.viper
def _law_near(vv, lq_k: int, hi: int) -> int:
    """A rise to the law's root nearest the pulse just measured (log2 charge lq_k): when g
    there asks for more charge, g at lq_k + 2**15 k (x sqrt 2 in charge) up to hi until it
    changes sign, and that interval searched; NOROOT if g at lq_k does not ask for more, or
    if none. For when the search's ends, Q_k/4 and 4 Q_k, have one sign: the law can still
    cross twice between them (a stable fixed point and an unstable one beyond it, as the
    calibration point is on an electrode whose mQ is nearly flat along the mE curve); the
    nearest above Q_k is the one the paper's iteration rises to from here, so the jump never
    passes it on the model. Rises only (lowering steps: the model-free rules, as before).
    Each evaluation is a unit of the jump's work."""
    v = ptr32(vv)
    if lq_k >= hi:  # (the pulse at or past the search's upper end: no rise to search)
        return NOROOT
    root = _root  # (one global lookup a call, not one a search)
    x0 = lq_k
    x = lq_k
    while True:
        if v[_V_WORK] >= FAST_MODEL_WORK_MAX:
            v[_V_CUT] = 1
            return NOROOT
        v[_V_WORK] += 1
        gx = int(root(vv, _K_LAW, x, x - 1, 0))
        if gx == NOROOT:
            return NOROOT
        if gx == 0 and x != lq_k:
            return x
        if gx <= 0:
            if x == lq_k:  # (no rise asked for)
                return NOROOT
            v[_V_FB] = gx + _V_BIAS  # [x0, x]: g(x0) > 0 >= g(x), g(x) known
            return int(root(vv, _K_LAW + _FB_KNOWN, x0, x, 0))
        x0 = x
        x = x0 + 0x8000
        if x > hi:
            x = hi
        if x <= x0:
            return NOROOT


@micropython.viper
def _law_fall(vv, lq_k: int, ask: int) -> int:
    """A fall past the search's lower end, Q_k/4 (lq_k: log2 of the charge just measured):
    when the law on the model asks at Q_k for less than Q_k x 2**(ask / 2**16) and at Q_k/4
    still for less than Q_k/4, its root from Q_k / 2**FAST_MODEL_FALL_LOG2 up to Q_k/4; else
    NOROOT (also if none). ask (SkinModel.jump): -_L_FALL_ASK, less than half; 0, any fall,
    on the reading after one on which the paper's step asked for less than half and the
    model gave no answer. Gel on a pulse at the duration ceiling asks for
    Q_k/5 ... Q_k/9. On electrodes whose mQ is nearly flat along the mE curve the law has a
    second fixed point far below a pulse settled at the ceiling, and a modest fall asked at
    Q_k (1/8, one Rp read 15 % low: review of session 27) found it and moved the settled
    pulse there for good (x 5 ... 8 in current, nothing felt); less than half is asked only
    by a reading of less than about half the Rp: gel on, or a read that wild (x 0.4 and
    below moves such a pulse there too; docs/controller.md). At the ceiling the mE curve's
    pulse of charge Q_k is longer than the pulse read, so after gel on the model can ask
    there for less than the reading does: validation seed 31 electrode 28 asked -0.73
    octave where the paper's step asked Q_k x 0.41, the model-free steps went, +50 % and
    then +38 % felt. Gating on the paper's step at one reading instead (session 28's first
    version) met it but let one read of about x 0.45 take the fall (its review: a pulse
    settled at the ceiling moved for good on 29 of 31 electrodes, and after a press back
    pulses felt up to +11.7 %); the model anchored on the next reading confirms it. Each
    evaluation is a unit of the jump's work."""
    v = ptr32(vv)
    root = _root
    x = lq_k
    while True:  # g at Q_k, then at Q_k/4
        if v[_V_WORK] >= FAST_MODEL_WORK_MAX:
            v[_V_CUT] = 1
            return NOROOT
        v[_V_WORK] += 1
        g = int(root(vv, _K_LAW, x, x - 1, 0))
        if g == NOROOT or g >= (ask if x == lq_k else 0):
            return NOROOT
        if x != lq_k:
            break
        x = lq_k - 0x20000
    v[_V_FB] = g + _V_BIAS  # [a, x]: g(x) < 0 known
    return int(root(vv, _K_LAW + _FB_KNOWN, lq_k - (FAST_MODEL_FALL_LOG2 << 16), x, 0))


@micropython.viper
def _law_q(vv, lq_k: int, ask: int) -> int:
    """The law's charge (1/16 pC) on the model skin in vv (SkinModel.v), for the pulse just
    measured of log2 charge lq_k: on the mE curve up to t_max (searched from Q_k/4 to
    4 Q_k, from Q_k on; with no root there, a rise to the nearest root above Q_k, else a
    fall past Q_k/4 that the model asks for at Q_k below ask, _law_fall), else on the line
    at t_max; NOROOT if none. Machine code
    with the values in vv: no attribute lookup (fixmath.exp2q inline)."""
    v = ptr32(vv)
    root = _root  # (one global lookup a call, not one a search)
    lq_max = v[_V_LQMAX]
    ltmax = v[_V_LTMAX]
    hi = lq_k + 0x20000
    if hi > lq_max:
        hi = lq_max
    lq_t = (v[_V_LME] + ltmax) >> 1  # the mE curve's charge at t_max
    if hi >= lq_t:
        hi = lq_t
        fb = int(root(vv, _K_LAW, hi, hi - 1, 0))
        if fb > 0:  # more than the curve gives at t_max
            lo = v[_V_LIMIN]
            hi = lq_max - ltmax
            x = v[_V_LIMAX]
            if x < hi:
                hi = x
            if hi <= lo:
                return NOROOT
            # g of the line at t_max is fb where the mE curve meets t_max (the same pulse, to the
            # rounding of lq_t), at I = xa; it falls with slope <= -1 in log2 I (the line's
            # charge L(Rp) does not rise with I: Rp(I, t_max) falls with I), so the root lies
            # in [xa, xa + fb]: searched there first, the whole range if it is not there
            xa = lq_t - ltmax
            x = NOROOT
            if fb > 32 and xa + fb < hi and lo < xa + fb:  # (fb > 32: g(xa) is fb to 23/2**16, the pulse's rounding)
                if xa >= lo:
                    v[_V_FB] = fb + _V_BIAS
                    x = int(root(vv, _K_CEIL + _FA_KNOWN, xa, xa + fb, 0))
                else:  # (the curve meets t_max below i_min: from i_min)
                    x = int(root(vv, _K_CEIL, lo, xa + fb, 0))
            if x == NOROOT and v[_V_CUT] == 0:
                x = int(root(vv, _K_CEIL, lo, hi, 0))
            if x == NOROOT:
                return NOROOT
            n = x + ltmax + 0x40000  # log2 of I t_max in 1/16 pC
        else:
            kind = _K_LAW
            if fb != NOROOT:  # g at hi is fb: the search does not evaluate it again
                v[_V_FB] = fb + _V_BIAS
                kind = _K_LAW + _FB_KNOWN
            n = int(root(vv, kind, lq_k - 0x20000, hi, lq_k))  # guess: the charge just delivered
            if n == NOROOT and v[_V_CUT] == 0:
                n = int(_law_near(vv, lq_k, hi))
                if n == NOROOT and v[_V_CUT] == 0:
                    n = int(_law_fall(vv, lq_k, ask))
            if n == NOROOT:
                return NOROOT
            n += 0x40000
    else:
        n = int(root(vv, _K_LAW, lq_k - 0x20000, hi, lq_k))
        if n == NOROOT and v[_V_CUT] == 0:
            n = int(_law_near(vv, lq_k, hi))
            if n == NOROOT and v[_V_CUT] == 0:
                n = int(_law_fall(vv, lq_k, ask))
        if n == NOROOT:
            return NOROOT
        n += 0x40000
    e = ptr32(_EXP_TAB)  # exp2q(n), inline
    k = (n & 0xFFFF) >> 10
    eu = n & 0x3FF
    n = n >> 16
    ea = e[k]
    eb = e[k + 1]
    w = eu >> 2
    m = ea + (((eb - ea) * eu + 512) >> 10) + ((w * (w - 256) * (e[k + 2] - eb - eb + ea) + 0x10000) >> 17)
    if n >= 22:
        return m << (n - 22)
    if n < -2:
        return 0
    return (m + (1 << (21 - n))) >> (22 - n)


class SkinModel:
    """The model's fitted parameters, the pulses it reads and its last answer. Built once
    by the Controller (`c`: its limits, mE and Eq. 3 are copied from it by limits/law).
    The pulses (the one just measured, the one before it) are kept in self.v (_V_NOW,
    _V_BEFORE), where the machine-code search reads them."""

    def __init__(self, c):
        self.c = c
        self.v = array("i", bytes(4 * _V_N))  # what _root reads (_V_*); the properties below
        self.v[_V_LS] = _V_BIAS
        self.v[_V_LC] = _V_BIAS
        self.rs_ohm = 0  # fitted: series resistance Rs
        self.beta_q16 = 0  # fitted: current exponent beta, Q.16
        self.lc_set = 0  # fitted: log2 Cp (pF) as set
        self.jump = self.jump  # MODE_FAST's call, bound once (found on the instance, not after a miss in its map)

    # words of self.v as attributes (the viper code reads and writes the words)
    on = word(_V_ON)  # 1: a model is set
    jumped = word(_V_JUMPED)  # 1: the pulse just measured was a model jump
    predicted_rp_ohm = word(_V_PRED)  # the Rp the model predicted for that jump
    ls = word(_V_LS, _V_BIAS)  # log2 S, anchored on the last jump
    lc = word(_V_LC, _V_BIAS)  # log2 Cp now (the two-pulse refit or the contact hypothesis may move it)
    tau_jumps = word(_V_TJ)  # model jumps anchored on the decay's tau (rule 7; counts up, saturating)
    tau_ok = word(_V_TCK)  # 1: rule 7 reads tau (set with its gain), 0: tau not used
    tau_gain_q16 = word(_V_TLK, _V_BIAS)  # log2 of the monitor's tau gain as set (Q.16)
    tau_checked = word(_V_TCHK)  # 1: this calibration's tau agreed with the fitted model (rule 7 reads tau)

    def set(self, rs_ohm, beta_q16, cp_pf):
        """The fitted parameters (Controller.set_skin has checked them); all 0: no model."""
        if rs_ohm == 0 and beta_q16 == 0 and cp_pf == 0:
            self.on = 0
        else:
            self.on = 1
            self.lc_set = log2q(cp_pf)
            self.lc = self.lc_set
        self.rs_ohm = rs_ohm
        self.beta_q16 = beta_q16
        self.v[_V_RS] = rs_ohm
        self.v[_V_BETA] = beta_q16
        self.v[_V_NI] = 0  # (nothing kept from a jump on other parameters)
        self.v[_V_ACH_OK] = 0
        self.set_tau(0, 0)  # (tau's gain comes with this fit's sweeps, or tau is not used)
        self.jumped = 0

    def limits(self, i_min_ua, i_max_ua, t_max_us, q_max_pc):
        """The controller's limits as the model reads them (Controller.set_limits)."""
        v = self.v
        v[_V_LTMAX] = log2q(t_max_us)
        v[_V_LIMIN] = log2q(i_min_ua)
        v[_V_LIMAX] = log2q(i_max_ua)
        v[_V_LQMAX] = log2q(q_max_pc)

    def law(self, c):
        """The law as the model reads it: log2 mE and Eq. 3 (Controller.calibrate)."""
        v = self.v
        v[_V_LME] = (log2q(c.i0_ua) << 1) + log2q(c.t0_us)
        v[_V_YQ4] = c._y_q4
        v[_V_MQN] = c._mq_num_pc
        v[_V_XS] = -c.x_star_ohm
        v[_V_MQD] = c._mq_den_ohm
        v[_V_LCAP] = c._line_cap_q4
        v[_V_LC] = self.lc_set + _V_BIAS  # a new calibration starts from the model as set (a Cp a refit or a tau
        v[_V_NI] = 0  # anchor adapted on the skin of an earlier arm is not carried into the next: `audit` replays from
        v[_V_ACH_OK] = 0  # the header's model, as set; review of session 25: 14 of 300 pulses of a second arm differed)
        v[_V_RFT] = 0
        v[_V_SNA] = 0
        v[_V_BFA] = 0
        v[_V_TLC] = 0
        v[_V_TPC] = 0  # (the skin of an earlier arm's taus may not be this one's)
        v[_V_TSTR] = 0
        k = c._k  # rule 7's check: the calibration pulse's tau (told before calibrate; taken here, never by an
        lt = k[_KC_LT]  # update) anchored with Rp0 must give the fitted Cp within FAST_TAU_CAL_AGREE
        k[_KC_LT] = 0
        v[_V_TCHK] = 0
        if v[_V_TCK] == 1 and lt > 0:
            ls0 = v[_V_LS]
            if int(anchor_tau(self, c.rp0_ohm, lt - (v[_V_TLK] - _V_BIAS), c.i0_ua, c.t0_us)):
                d = v[_V_LC] - (self.lc_set + _V_BIAS)
                if -FAST_TAU_CAL_AGREE <= d <= FAST_TAU_CAL_AGREE:
                    v[_V_TCHK] = 1
            v[_V_LS] = ls0
            v[_V_LC] = self.lc_set + _V_BIAS

    def set_tau(self, ok, gain_q16):
        """Rule 7: ok 1: the jump reads the decay's tau, gain_q16 (log2 of the monitor's tau over the skin's, as
        the host measured it on this fit's sweeps; |gain| <= SKIN_TAU_MAX_Q16) taken out of it; ok 0: tau not used.
        (Controller.set_skin has checked them.)"""
        v = self.v
        v[_V_TCK] = 1 if ok else 0
        v[_V_TLK] = (gain_q16 if ok else 0) + _V_BIAS
        v[_V_TPC] = 0
        v[_V_TCHK] = 0  # (checked at the next calibration)
        if v[_V_TLC]:
            v[_V_LC] = self.lc_set + _V_BIAS  # (a tau anchor's Cp is not carried over)
            v[_V_TLC] = 0

    @micropython.native
    def rp(self, ls, lc, li, lt):
        """Rp (ohm, at most 2**21) of the model skin with log2 S = ls, log2 Cp = lc for a
        pulse with log2 I = li, log2 T = lt (_root's model, read as an anchor on Rp 0)."""
        v = self.v
        v[_V_PROBE + _P_LI] = li
        v[_V_PROBE + _P_LT] = lt
        return _root(v, _K_RP + (_V_PROBE << 8), ls, ls - 1, lc)

    @micropython.viper
    def refit_cp(self, up: int) -> int:
        """Two-pulse refit: log2 Cp with which the model reads both the pulse just measured
        and the one before (the less charged of the two gives Cp, the other S), taken
        when within 1/8 of the Cp set ... up (log2 Q.16) above it; returns 1 when taken.
        (viper: Rs, beta and the pulses from self.v.)"""
        vv = self.v
        v = ptr32(vv)
        b = v[_V_BETA]  # mul_q16(x, beta), inline below (beta >= 0)
        ma = v[_V_BEFORE + _P_LI] - _L_1MA
        mc = 0 - ma if ma < 0 else ma
        my = (((mc >> 10) * b) >> 6) + (((mc & 0x3FF) * b) >> 16)
        z0 = v[_V_BEFORE + _P_LT] + (0 - my if ma < 0 else my)  # log2 T/tau, less log2 (S Cp / 1e6)
        ma = v[_V_NOW + _P_LI] - _L_1MA
        mc = 0 - ma if ma < 0 else ma
        my = (((mc >> 10) * b) >> 6) + (((mc & 0x3FF) * b) >> 16)
        z1 = v[_V_NOW + _P_LT] + (0 - my if ma < 0 else my)
        if z0 > z1:
            p = _V_NOW
            o = _V_BEFORE
        else:
            p = _V_BEFORE
            o = _V_NOW
        d = v[p + _P_RP] - v[_V_RS]
        if d >= 16:
            lo = int(log2q(d + 2))  # R - (Rp - Rs) = 2 ohm: the pulse charged Cp fully
            kind = _K_TWO + (p << 8) + (o << 16)
            lr = int(_root(vv, kind, lo, lo + 0x40000, 0))
            if lr != NOROOT:
                _root(vv, kind, lr, lr - 1, 0)  # (sets _V_LCTWO for the root itself)
                lc = v[_V_LCTWO] - _V_BIAS
                lc_set = int(self.lc_set)
                if lc_set - 0x30000 <= lc and lc <= lc_set + up:
                    v[_V_LC] = lc + _V_BIAS  # (self.lc)
                    return 1
        return 0

    @micropython.viper
    def jump(self, qf: int, q_k: int, rp_ohm: int, i_k: int, t_k: int, jumped: int, prev, from_q) -> int:
        """MODE_FAST's jump with the skin model: the law solved on the model anchored
        to the pulse just measured (i_k, t_k; Rp = rp_ohm, or the drift's prediction;
        prev: the controller's int array c._k, whose words _KB_* hold the pulse before it,
        c.before, Rp 0 if none). After a model jump
        that missed its prediction and moved I, Cp is refitted first. On a fresh rise (no
        model jump before, or a reading that missed it by more than Rp/2**FAST_MODEL_STEP_LOG2
        with no refit taken or a refit refused: Cp above the fitted one by FAST_MODEL_CP_ABOVE),
        the contact hypothesis is also solved and the smaller charge taken. Returns the
        status, or -1 when the model has no answer (the caller goes on without it), -2
        when a root search ran out of FAST_MODEL_WORK_MAX (the caller takes the paper's
        step: never the larger hydration answer nor a search's unfinished value).
        A fresh rise (or one after a miss above Rp/2**FAST_MODEL_STEP_LOG2 of a model a refit had
        set, refit or not) into the duration ceiling that the model predicts to raise Rp by more
        than 1/8 is halved (docs/controller.md, rule 6).
        q_k is i_k * t_k (its log2 is computed with the pulse's words, below); from_q is the core's Eq. 4
        with the bounds (sensation_core._from_q). (viper: the model's state from self.v;
        self.ls, .lc, .jumped, .predicted_rp_ohm are its words.)"""
        vv = self.v
        v = ptr32(vv)
        pk = ptr32(prev)
        root = _root  # (one global lookup a jump, not one a search)
        p0rp = pk[_KB_RP]
        bhit = 0  # the pulse before is the last jump's pulse: its anchor, if any, is known
        # the last jump saw a step of the skin on the pulse before and gave no answer: both pulses
        # are on the skin as it is now (rule 4's refit applies to them)
        bstep = 1 if (p0rp > 0 and v[_V_SNA] != 0 and v[_V_SNA_I] == pk[_KB_I] and v[_V_SNA_T] == pk[_KB_T]) else 0
        # _law_fall's ask at Q_k: the law on the model asks for less than half of Q_k; or for less at all on the
        # reading after one on which the paper's step asked for less than half and the model gave no answer (the
        # model anchored on this second reading confirms the fall: one bad read of about half the Rp must not take
        # it, and after one the model on the honest reading asks for more)
        ask = 0 - _L_FALL_ASK
        if p0rp > 0 and v[_V_BFA] != 0 and v[_V_BFA_I] == pk[_KB_I] and v[_V_BFA_T] == pk[_KB_T]:
            ask = 0
        if qf < (q_k << 3):
            v[_V_BFA] = 1  # (cleared below when the jump gives an answer)
            v[_V_BFA_I] = i_k
            v[_V_BFA_T] = t_k
        else:
            v[_V_BFA] = 0
        v[_V_SNA] = 0
        j = 3  # the log2 words to compute (below): from j = 0 the pulse before's too
        if p0rp > 0:
            v[_V_BEFORE + _P_RP] = p0rp
            if v[_V_NI] == pk[_KB_I] and v[_V_NT] == pk[_KB_T] and v[_V_NOW + _P_RP] == p0rp:
                v[_V_BEFORE + _P_LI] = v[_V_NOW + _P_LI]  # its words: the last jump's pulse's
                v[_V_BEFORE + _P_LT] = v[_V_NOW + _P_LT]
                v[_V_BEFORE + _P_RLP] = v[_V_NOW + _P_RLP]
                bhit = v[_V_ACH_OK]
            else:
                j = 0
        bls = v[_V_ACH_LS]
        blc = v[_V_ACH_LC]
        bw = v[_V_ACH_W]
        # log2 I, T, Rp of the pulse before (j 0-2, when computed) and of the pulse just measured
        # (j 3-5), and log2 Q of the latter (j 6): fixmath.log2q inline (a call is ~9 us on the chip)
        v[_V_NOW + _P_RP] = rp_ohm
        v[_V_WORK] = 0
        v[_V_CUT] = 0
        g2 = ptr32(_LOG_TAB)
        while j < 7:
            if j == 0:
                n = pk[_KB_I]
            elif j == 1:
                n = pk[_KB_T]
            elif j == 2:
                n = p0rp
            elif j == 3:
                n = i_k
            elif j == 4:
                n = t_k
            elif j == 5:
                n = rp_ohm
            else:
                n = i_k * t_k
            if n < 1:
                n = 1
            k = 22
            if n >= 0x800000:  # to [2**22, 2**23): a binary search (a shift loop is ~0.6 us a bit on the chip)
                if n >= 0x4000000:
                    n >>= 4
                    k += 4
                if n >= 0x1000000:
                    n >>= 2
                    k += 2
                if n >= 0x800000:
                    n >>= 1
                    k += 1
            else:
                if n < 0x80:
                    n <<= 16
                    k -= 16
                if n < 0x8000:
                    n <<= 8
                    k -= 8
                if n < 0x80000:
                    n <<= 4
                    k -= 4
                if n < 0x200000:
                    n <<= 2
                    k -= 2
                if n < 0x400000:
                    n <<= 1
                    k -= 1
            eu = (n >> 16) - 64
            ea = g2[eu]
            eb = g2[eu + 1]
            m = n & 0xFFFF
            w = m >> 8
            n = (k << 16) + ea + (((eb - ea) * m + 0x8000) >> 16) + ((w * (w - 256) * (g2[eu + 2] - eb - eb + ea) + 0x10000) >> 17)
            if j == 0:
                v[_V_BEFORE + _P_LI] = n
            elif j == 1:
                v[_V_BEFORE + _P_LT] = n
            elif j == 2:
                v[_V_BEFORE + _P_RLP] = n
            elif j == 3:
                v[_V_NOW + _P_LI] = n
            elif j == 4:
                v[_V_NOW + _P_LT] = n
            elif j == 5:
                v[_V_NOW + _P_RLP] = n
            else:
                v[_V_LQK] = n
            j += 1
        v[_V_NI] = i_k
        v[_V_NT] = t_k
        v[_V_ACH_OK] = 0
        lt = pk[_KC_LTU]  # rule 7: the decay after the pulse read a tau (its gain set with the model): S and Cp
        tauf = 0  # from it and this Rp at once
        if lt > 0 and v[_V_TCHK] == 1:  # (checked at this calibration: a gain is set, _V_TCK 1)
            lt -= v[_V_TLK] - _V_BIAS  # (the monitor's tau gain out)
        else:
            lt = 0
        if lt > 0:
            ls0 = v[_V_LS]
            lc0 = v[_V_LC]
            if int(anchor_tau(self, rp_ohm, lt, i_k, t_k)):
                pc = v[_V_TPC]
                v[_V_TPC] = v[_V_LC]
                d = v[_V_LC] - pc
                if pc != 0 and (d if d >= 0 else 0 - d) <= FAST_TAU_AGREE:
                    tauf = 1  # (two reads agree on Cp)
                    if v[_V_TSTR] > 0:
                        v[_V_TSTR] -= 1
                elif pc != 0:
                    v[_V_TSTR] += 1
                    if v[_V_TSTR] >= FAST_TAU_STRIKES:
                        v[_V_TCHK] = 0  # (tau off until the next calibration)
            else:
                v[_V_TPC] = 0
            if tauf == 0:
                v[_V_LS] = ls0  # (the anchor not taken: the model as it was)
                v[_V_LC] = lc0
        if tauf:
            v[_V_TLC] = 1
            v[_V_RFT] = 0  # (no refit, no contact hypothesis, no halving: Cp is read, not inferred)
            v[_V_SNA] = 0
            fresh = 0
            bigm = 0
            unchk = 0
            ls = v[_V_LS] - _V_BIAS
            lc = v[_V_LC] - _V_BIAS
            q16 = int(_law_q(vv, v[_V_LQK], ask))
            if q16 == NOROOT:
                return -2 if v[_V_CUT] else -1
        else:
            if v[_V_TLC]:  # the last tau anchor's Cp is not carried into rules 1-6: the fitted one (a bad reading
                v[_V_LC] = int(self.lc_set) + _V_BIAS  # with its tau left Cp x 1.75 for the jumps without tau that
                v[_V_TLC] = 0  # followed: +12.6 % felt, review of session 25)
            fresh = 1 if jumped == 0 else 0  # rules 3 and 6: the model not checked on this skin
            step = 0  # a step of the skin seen on the pulse just measured
            bigm = 0  # a model checked by a refit missed by more than Rp/2**FAST_MODEL_STEP_LOG2 (rule 6)
            unchk = 0  # a refitted Cp not yet checked by a pulse that moved I
            rft = v[_V_RFT]
            v[_V_RFT] = 0
            if jumped and p0rp > 0:
                miss = rp_ohm - v[_V_PRED]
                dl = v[_V_NOW + _P_LI] - v[_V_BEFORE + _P_LI]
                adl = dl if dl >= 0 else 0 - dl
                am = miss if miss >= 0 else 0 - miss
                big = 1 if am > (rp_ohm >> FAST_MODEL_STEP_LOG2) else 0
                step = big
                bigm = big & rft  # (a miss after a contact hypothesis is what the refit is for: rule 3)
                if rft and adl <= _L_MOVED:
                    unchk = 1  # a pulse that hardly moved I does not check a refitted Cp (its pair may
                    # straddle a second step: review of session 18)
                if am > (rp_ohm >> 9) and adl > _L_REFIT:
                    if int(self.refit_cp(FAST_MODEL_CP_ABOVE if big else 0x10000)):
                        v[_V_RFT] = 1
                    elif big:
                        fresh = 1
                elif big:
                    fresh = 1
            elif p0rp > 0:
                dl = v[_V_NOW + _P_LI] - v[_V_BEFORE + _P_LI]
                adl = dl if dl >= 0 else 0 - dl
                dt = v[_V_NOW + _P_LT] - v[_V_BEFORE + _P_LT]
                # on one skin log Rp moves by at most |log I| + |log T| between two pulses (the current
                # exponent beta < 1; d ln Rp / d ln T <= 1): by more than that and 1/8, the skin stepped
                dr = v[_V_NOW + _P_RLP] - v[_V_BEFORE + _P_RLP]
                if (dr if dr >= 0 else 0 - dr) - adl - (dt if dt >= 0 else 0 - dt) > _L_STEP:
                    step = 1
                elif bstep and adl > _L_REFIT:
                    # the pulse before saw the step and had no answer: the pair is on one skin, refit
                    v[_V_RFT] = int(self.refit_cp(FAST_MODEL_CP_ABOVE))
                elif rft and adl <= _L_MOVED:
                    unchk = 1  # (as above: the last call's refit, its jump unanswered, not yet checked)
            if step:  # (cleared below when the jump gives an answer)
                v[_V_SNA] = 1  # (not rp_ohm: the drift's prediction, where the pulse before keeps the reading)
                v[_V_SNA_I] = i_k
                v[_V_SNA_T] = t_k
            lc = v[_V_LC] - _V_BIAS  # (self.lc)
            w0 = v[_V_WORK]
            ls = int(root(vv, _K_ANCHOR + (_V_NOW << 8), 0, 0, lc))  # anchor S on the pulse just measured
            if ls == NOROOT:
                return -2 if v[_V_CUT] else -1
            v[_V_LS] = ls + _V_BIAS  # (self.ls)
            v[_V_ACH_LS] = ls + _V_BIAS  # (kept for the next jump's pulse before)
            v[_V_ACH_LC] = lc + _V_BIAS
            v[_V_ACH_W] = v[_V_WORK] - w0
            v[_V_ACH_OK] = 1
            lq_k = v[_V_LQK]
            q16 = int(_law_q(vv, lq_k, ask))
            lc_set = int(self.lc_set) if q16 == NOROOT else lc
            if q16 == NOROOT and v[_V_CUT] == 0 and lc > lc_set:
                # no fixed point on the model refitted to a larger Cp (its gain along the mE curve
                # passes 1): the fitted Cp back, S anchored anew, the law once more (docs/controller.md, rule 4)
                lc = lc_set
                v[_V_LC] = lc + _V_BIAS  # (self.lc)
                v[_V_ACH_OK] = 0
                w0 = v[_V_WORK]
                ls = int(root(vv, _K_ANCHOR + (_V_NOW << 8), 0, 0, lc))
                if ls == NOROOT:
                    return -2 if v[_V_CUT] else -1
                v[_V_LS] = ls + _V_BIAS  # (self.ls)
                v[_V_ACH_LS] = ls + _V_BIAS
                v[_V_ACH_LC] = lc + _V_BIAS
                v[_V_ACH_W] = v[_V_WORK] - w0
                v[_V_ACH_OK] = 1
                q16 = int(_law_q(vv, lq_k, ask))
            if q16 == NOROOT:
                return -2 if v[_V_CUT] else -1
            if q16 > (q_k << 4) and fresh and p0rp > 0:
                # a fresh rise: hydration (S alone) or contact (S and Cp)? The contact's
                # charge is the smaller one; take it, the next pulse tells them apart
                if bhit and blc == lc + _V_BIAS and v[_V_WORK] + bw <= FAST_MODEL_WORK_MAX:
                    # the last jump's anchor on that pulse at that Cp, its work charged as if it ran
                    # (its search would not have run out: the same answers as searching again)
                    ls0 = bls - _V_BIAS
                    v[_V_WORK] += bw
                else:
                    ls0 = int(root(vv, _K_ANCHOR + (_V_BEFORE << 8), 0, 0, lc))  # and on the one before
                if ls0 != NOROOT:
                    v[_V_BEFORE + _P_LS] = ls0 + _V_BIAS
                    la = int(root(vv, _K_PEEL + (_V_NOW << 8) + (_V_BEFORE << 16), -0x30000, 0x10000, 0))
                    if la != NOROOT:
                        ls1 = ls
                        lc1 = lc
                        mb = v[_V_BETA] - 0x10000  # ls0 + mul_q16(la, beta - 1), inline
                        ma = 0 - la if la < 0 else la
                        mc = 0 - mb if mb < 0 else mb
                        my = (((ma >> 10) * mc) >> 6) + (((ma & 0x3FF) * mc) >> 16)
                        if la < 0:
                            my = my if mb < 0 else 0 - my
                        elif mb < 0:
                            my = 0 - my
                        ls = ls0 + my
                        lc = lc1 + la
                        v[_V_LS] = ls + _V_BIAS  # (self.ls, self.lc)
                        v[_V_LC] = lc + _V_BIAS
                        q2 = int(_law_q(vv, lq_k, ask))
                        if q2 != NOROOT and q2 < q16:
                            q16 = q2
                        else:
                            ls = ls1
                            lc = lc1
                            v[_V_LS] = ls + _V_BIAS
                            v[_V_LC] = lc + _V_BIAS
                if v[_V_CUT]:  # the contact's charge is unknown: not the hydration's either
                    return -2
        # the paper's direction only, and a rise of at most FAST_MODEL_RAISE paper steps
        base = q_k << 4
        step = qf - base
        if step == 0 or (q16 > base and step < 0) or (q16 <= base and step > 0):
            return -1
        # (the shift's test first: step << FAST_MODEL_RAISE_LOG2 is formed only when it is <= q16 - base < 2**30,
        # for every step: a guard step < 2**22 used to skip the cap on larger steps, review of session 14)
        if step > 0 and ((q16 - base) >> FAST_MODEL_RAISE_LOG2) >= step and q16 - base > (step << FAST_MODEL_RAISE_LOG2):
            q16 = base + (step << FAST_MODEL_RAISE_LOG2)
        c = self.c
        s_k = pk[_KC_ST]  # (c.status)
        st = int(from_q(c, q16))
        if unchk and q16 > base and (st & _ST_T_MAX) != 0 and (s_k & _ST_T_MAX) == 0 and pk[_KC_I] > i_k:
            # an unchecked refit's rise into the ceiling at a higher current: at most the
            # model-free bound there (fast_step.ceiling_bound)
            qh = int(ceiling_bound(prev, q_k, rp_ohm, qf >> 4, i_k))
            if (q16 >> 4) > qh:  # (then qh << 4 < q16 < 2**30)
                q16 = qh << 4
                unchk = 2  # held: rule 6 does not halve it again (below I_k, Rp would rise)
                pk[_KC_I] = i_k  # (c.i_ua, c.t_us)
                pk[_KC_T] = t_k
                st = int(from_q(c, q16))
        v[_V_PROBE + _P_LI] = pk[_KC_I]  # the pulse sent (c.i_ua, c.t_us): the model's prediction of its Rp
        v[_V_PROBE + _P_LT] = pk[_KC_T]
        rp = int(root(vv, _K_RP + (_V_PROBE << 8) + _RAW_IT, ls, ls - 1, lc))
        if (q16 > base and (fresh or bigm) and unchk != 2 and (st & _ST_T_MAX) != 0 and (s_k & _ST_T_MAX) == 0
                and rp - rp_ohm > (rp_ohm >> FAST_MODEL_RP_RISE_LOG2)):
            # a fresh rise (the model not yet checked on this skin: the pulse just measured
            # was no model jump) that enters the duration ceiling, where the model moves I at
            # t_max, and predicts Rp to rise by more than 1/2**FAST_MODEL_RP_RISE_LOG2: half of
            # the rise now; the next pulse re-anchors the model (and refits Cp) on its reading
            q16 = base + ((q16 - base) >> 1)
            pk[_KC_I] = i_k  # (c.i_ua, c.t_us)
            pk[_KC_T] = t_k
            st = int(from_q(c, q16))
            v[_V_PROBE + _P_LI] = pk[_KC_I]
            v[_V_PROBE + _P_LT] = pk[_KC_T]
            rp = int(root(vv, _K_RP + (_V_PROBE << 8) + _RAW_IT, ls, ls - 1, lc))
        v[_V_PRED] = rp  # (self.predicted_rp_ohm, self.jumped)
        v[_V_JUMPED] = 1
        v[_V_SNA] = 0
        v[_V_BFA] = 0
        n = pk[_KC_MJ]  # (c.model_jumps)
        if n < _SAT30:
            pk[_KC_MJ] = n + 1
        n = v[_V_TJ]  # (self.tau_jumps)
        if tauf and n < _SAT30:
            v[_V_TJ] = n + 1
        return st
