"""One evaluation of the skin model inside shared/skin_model.py `_root` (machine code on the
chip: its set-up per search and its inline log2 / 2**x, docs/performance.md "One evaluation
of the model, cheaper"):
- evaluations at fixed points of the search ranges of the first 120 golden skin streams
  equal the model's formula written plainly with fixmath (log2q, exp2q, mul_q16, muldiv)
  (every evaluation the golden streams make is covered by their hashes, tests/test_core_golden.py);
- the divisions of the small-z series replaced by multiply-shifts are exact over the whole
  range their operands can take (exhaustive), and that range is what the code says."""

import gzip
import json
import sys
from array import array

import pytest

import skin_model as sm
from fixmath import exp2q, log2q, mul_q16, muldiv

from conftest import ROOT

sys.path.insert(0, str(ROOT / "tests" / "golden"))
import replay  # noqa: E402

DATA = json.loads(gzip.decompress((ROOT / "tests" / "golden" / "core_traces.json.gz").read_bytes()))
SKIN = [c["ops"] for c in DATA["cases"] if c["name"].startswith("skin/")]
SEARCHES = (sm._K_ANCHOR, sm._K_PEEL, sm._K_LAW, sm._K_CEIL, sm._K_TWO)
B = sm._V_BIAS


def model_rp(v, ls, lc, li, lt):
    """The model's Rp (ohm) for log2 S, log2 Cp, log2 I, log2 T (Q.16): module docstring's
    formula, 2**x and e**-z as skin_model computes them, with fixmath's functions."""
    rs = v[sm._V_RS]
    lr = ls - mul_q16(li - sm._L_1MA, v[sm._V_BETA])  # log2 R(I)
    lz = lt - lr - lc + sm._L_1E6  # log2 (T / (R Cp))
    if lz < -0x10000:  # z < 1/2: (T / Cp) (1 - e**-z) / z, the series in Q.14
        lrz = lt - lc + sm._L_1E6
        if lrz > sm._L_R_MAX:
            return 0x200000
        z = exp2q(lz + 0xE0000) if lz > -0x1E0000 else 0
        u = 16384 - z // 5
        u = 16384 - ((z * u) >> 14) // 4
        u = 16384 - ((z * u) >> 14) // 3
        u = 16384 - ((z * u) >> 14) // 2
        r = exp2q(lrz)
        return rs + (((r >> 10) * u + (((r & 0x3FF) * u) >> 10) + 8) >> 4)
    if lr > sm._L_R_MAX:
        return 0x200000
    if lz > sm._L_Z12:
        u = 0x8000
    else:
        z = exp2q(lz + 0x100000)  # z in Q.16
        lw = -((((z >> 8) * sm._L_E) >> 8) + (((z & 0xFF) * sm._L_E) >> 16))  # log2 e**-z
        u = 0x8000 - exp2q(lw + 0xF0000)  # 1 - e**-z in Q.15
    r = exp2q(lr)
    return rs + (((r >> 10) * u + (((r & 0x3FF) * u) >> 10) + 16) >> 5)


def line_q4(v, rp):
    """Eq. 3 on the model's Rp (1/16 pC), as the controller's _line."""
    rp = min(rp, sm._RP_MAX_OHM)
    return v[sm._V_YQ4] + muldiv(v[sm._V_MQN], rp + v[sm._V_XS], v[sm._V_MQD], 4, v[sm._V_LCAP])


def g_ref(v, kind, x, lc0):
    """g(kind, x) (and the _V_LCTWO word a _K_TWO evaluation writes, else None)."""
    k = kind & 0xFF
    pb = (kind >> 8) & 0xFF
    ob = (kind >> 16) & 0xFF
    beta = v[sm._V_BETA]
    if k in (sm._K_ANCHOR, sm._K_RP):
        rp = model_rp(v, x, lc0, v[pb + sm._P_LI], v[pb + sm._P_LT])
        return (rp if k == sm._K_RP else log2q(rp) - v[pb + sm._P_RLP]), None
    if k == sm._K_PEEL:
        ls = v[ob + sm._P_LS] - B + mul_q16(x, beta - 0x10000)
        rp = model_rp(v, ls, v[sm._V_LC] - B + x, v[pb + sm._P_LI], v[pb + sm._P_LT])
        return log2q(rp) - v[pb + sm._P_RLP], None
    if k == sm._K_LAW:
        rp = model_rp(v, v[sm._V_LS] - B, v[sm._V_LC] - B, v[sm._V_LME] - x, 2 * x - v[sm._V_LME])
        return log2q(line_q4(v, rp)) - (x + 0x40000), None
    if k == sm._K_CEIL:
        rp = model_rp(v, v[sm._V_LS] - B, v[sm._V_LC] - B, x, v[sm._V_LTMAX])
        return log2q(line_q4(v, rp)) - (x + v[sm._V_LTMAX] + 0x40000), None
    assert k == sm._K_TWO
    my = x - log2q(exp2q(x) - v[pb + sm._P_RP] + v[sm._V_RS])  # log2 (R / (R - Rp + Rs))
    if my <= 0:
        return sm.NOROOT, None
    lc = v[pb + sm._P_LT] - x + sm._L_1E6 - (log2q(my) - 0x100000 + sm._L_LN2)
    ls = x + mul_q16(v[pb + sm._P_LI] - sm._L_1MA, beta)
    rp = model_rp(v, ls, lc, v[ob + sm._P_LI], v[ob + sm._P_LT])
    return log2q(rp) - v[ob + sm._P_RLP], lc + B


@pytest.fixture(scope="module")
def searches():
    """Every search _root runs in 120 golden skin streams: (kind, a, b, lc0, the values before)."""
    seen = []
    real = sm._root

    def spy(vv, kind, a, b, lc0):
        if b >= a and (kind & 0xFF) in SEARCHES:
            seen.append((kind, a, b, lc0, array("i", vv)))
        return real(vv, kind, a, b, lc0)

    sm._root = spy
    try:
        for line in SKIN[:120]:
            replay.run(line, [])
    finally:
        sm._root = real
    return seen


def test_each_evaluation_is_the_models_formula(searches):
    kinds = {}
    n = 0
    for kind, a, b, lc0, v in searches:
        if kind & 0xFF == sm._K_ANCHOR:  # (finds its own range: its evaluations are _K_RP's)
            pb = kind & 0xFF00
            ma = v[(pb >> 8) + sm._P_LI] - sm._L_1MA
            a = log2q(max(v[(pb >> 8) + sm._P_RP] - v[sm._V_RS], 1)) + mul_q16(ma, v[sm._V_BETA])
            b = a + 0x40000
            kind = sm._K_RP + pb
        else:
            kind &= 0xFFFFFF  # (not _FB_KNOWN / _FA_KNOWN: one evaluation, nothing known)
        w = b - a
        for x in (a, b, a + w // 2, a + w // 3, a + (w * 7) // 8, a + 1, b - 1):
            vv = array("i", v)
            got = sm._root(vv, kind, x, x - 1, lc0)
            want, lctwo = g_ref(v, kind, x, lc0)
            assert got == want, (kind, x, lc0, list(v))
            if lctwo is not None:
                assert vv[sm._V_LCTWO] == lctwo
            kinds[kind & 0xFF] = kinds.get(kind & 0xFF, 0) + 1
            n += 1
    # every kind of evaluation was checked, many times
    assert set(kinds) == {sm._K_RP, sm._K_PEEL, sm._K_LAW, sm._K_CEIL, sm._K_TWO}, kinds
    assert min(kinds.values()) >= 100 and n >= 10000, kinds


def test_the_series_multiply_shifts_are_exact_over_their_whole_range():
    # z = exp2q(lz + 0xE0000) for lz in (-0x1E0000, -0x10000), the series' range (else z = 0):
    # exp2q rises with its argument, so its last value is the largest; all of them checked
    zs = {exp2q(n) for n in range(-0x1E0000 + 1 + 0xE0000, -0x10000 + 0xE0000)}
    z_max = max(zs)
    assert min(zs) >= 0 and z_max == exp2q(-0x10000 - 1 + 0xE0000) <= 1 << 13
    # every operand of // 5, // 4, // 3, // 2 in the series is in [0, z_max]: z itself, and
    # (z * u) >> 14 with u in [0, 16384]; over that range, and well beyond it
    for y in range(0, 1 << 14):
        assert (y * 52429) >> 18 == y // 5 and y * 52429 < 1 << 30
        assert (y * 43691) >> 17 == y // 3 and y * 43691 < 1 << 30
        assert y >> 2 == y // 4 and y >> 1 == y // 2
    for z in range(z_max + 1):  # the whole series, both ways, and u's range
        u = 16384 - z // 5
        assert 0 <= u <= 16384
        for d in (4, 3, 2):
            t = (z * u) >> 14
            assert 0 <= t <= z
            u = 16384 - t // d
            assert 0 <= u <= 16384


def test_the_tables_differences_are_fixmaths_and_never_negative():
    # (a 64-bit viper reads ptr32 words unsigned: the MicroPython unix port would misread a negative one)
    from fixmath import _EXP_TAB, _LOG_TAB

    t = sm._TAB
    assert min(t) >= 0 and len(t) == 384
    for k in range(64):
        e, g = _EXP_TAB, _LOG_TAB
        assert t[k] == e[k] and t[sm._T_E1 + k] == e[k + 1] - e[k] and t[sm._T_E2 + k] == e[k + 2] - 2 * e[k + 1] + e[k]
        assert t[sm._T_G + k] == g[k] and t[sm._T_G1 + k] == g[k + 1] - g[k]
        assert t[sm._T_G2 + k] == -(g[k + 2] - 2 * g[k + 1] + g[k])
