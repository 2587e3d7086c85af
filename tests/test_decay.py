"""decay.ltau_q16: log2 of the monitor's decay time constant after the fall, from the
ADC samples (shared/decay.py). Against the two-window formula in floats and the true
tau of a synthetic decay; its refusals; bit-identical in the MicroPython VM (viper,
compiled for this CPU as on the chip) and allocation-free under the heap lock."""

import json
import math
from array import array

from hypothesis import given, settings
from hypothesis import strategies as st

import decay

from conftest import UNDER_HEAP_LOCK, run_mp

DT = 2  # us a sample (the RP2040's ADC at 500 ksps)


def samples(tau_us, amp_counts, off_counts, n, dt=DT, noise=None):
    """n samples of off + amp exp(-(k + 1) dt / tau), rounded to counts and clipped to 0..4095."""
    out = array("H", [0] * n)
    for k in range(n):
        x = off_counts + amp_counts * math.exp(-(k + 1) * dt / tau_us) + (noise[k] if noise else 0.0)
        out[k] = min(4095, max(0, int(x + 0.5)))
    return out


def two_windows(buf, n, off_x16, dt):
    m = n // 2
    sa = sum(buf[k] * 16 - off_x16 for k in range(m))
    sb = sum(buf[m + k] * 16 - off_x16 for k in range(m))
    return m * dt / math.log(sa / sb)


@settings(max_examples=300, deadline=None)
@given(tau=st.floats(20.0, 5000.0), amp=st.integers(200, 3500), off=st.integers(0, 400), n=st.integers(8, 400))
def test_log2_tau_is_the_two_window_formula_and_near_the_true_tau(tau, amp, off, n):
    buf = samples(tau, amp, off, n)
    lt = decay.ltau_q16(buf, 0, n, off * 16, DT)
    m = n // 2
    sa = sum(buf[k] * 16 - off * 16 for k in range(m))
    sb = sum(buf[m + k] * 16 - off * 16 for k in range(m))
    if sa < m * 16 * decay.MIN_LEVEL_COUNTS or sa - sb < m * 16 * decay.MIN_DROP_COUNTS:
        assert lt == 0  # no decay to read: its level or its drop within the noise of a flat record
        return
    if buf[m * 2 - 1] <= off:  # decayed into the offset within the capture: coarse
        return
    assert lt > 0
    exact = two_windows(buf, n, off * 16, DT)
    # the integer path: log2q's error (< 2**-16 a call) on Sa, Sb, then on their difference d (Q.16),
    # which is small where tau is long against the windows: 2 units of d are 2 / (d ln 2) in log2 d
    d = math.log2(((n // 2) * DT / exact) / math.log(2)) + 16  # log2 of d in Q.16 units
    assert abs(lt / 65536 - math.log2(exact)) < 4e-4 + 3 / (2 ** d * math.log(2)), (lt / 65536, math.log2(exact))
    # against the true tau: the counts' rounding only (no noise here). Each of the 2m samples is off by
    # up to 1/2 count, so Sa - Sb (about m amp span) by up to m: tau's relative error up to
    # 1 / (amp span), large where the windows' sums differ little (tau much longer than the capture)
    ratio = 2 ** (lt / 65536) / tau
    span = (n // 2) * DT / tau  # ln(Sa / Sb)
    assert abs(ratio - 1) < 0.02 + 1.0 / (amp * span) + 0.5 / (amp * math.exp(-span * 2)), (ratio, span)


def test_what_cannot_be_read_is_zero():
    buf = samples(100.0, 2000, 100, 64)
    assert decay.ltau_q16(buf, 0, 64, 1600, DT) > 0
    assert decay.ltau_q16(buf, 0, 3, 1600, DT) == 0  # fewer than N_MIN samples
    assert decay.ltau_q16(buf, 0, decay.N_MAX + 1, 1600, DT) == 0
    assert decay.ltau_q16(buf, 0, 64, 1600, 0) == 0 and decay.ltau_q16(buf, 0, 64, 1600, decay.DT_MAX_US + 1) == 0
    flat = array("H", [500] * 64)
    assert decay.ltau_q16(flat, 0, 64, 100 * 16, DT) == 0  # no decay: Sa == Sb
    rising = array("H", range(100, 164))
    assert decay.ltau_q16(rising, 0, 64, 0, DT) == 0
    assert decay.ltau_q16(buf, 0, 64, 4095 * 16, DT) == 0  # the offset above every sample: Sb <= 0
    noisy = array("H", [100 + (k * 7919) % 7 for k in range(64)])  # a resistor's nothing after the fall, noise 0..6
    assert two_windows(noisy, 64, 0, DT) > 0 and decay.ltau_q16(noisy, 0, 64, 0, DT) == 0  # Sa > Sb by noise alone
    low = samples(200.0, 15, 0, 64)  # a decay of 15 counts: below MIN_LEVEL_COUNTS
    assert decay.ltau_q16(low, 0, 64, 0, DT) == 0 and decay.ltau_q16(samples(200.0, 60, 0, 64), 0, 64, 0, DT) > 0
    slow = array("H", [4095] * 512 + [4091] * 512)  # drops 4 counts: tau 512 dt / ln(4095 / 4091)
    assert decay.ltau_q16(slow, 0, 1024, 0, 1000) == 0  # 5.2e8 us: beyond LTAU_END (1 s)
    assert 0 < decay.ltau_q16(slow, 0, 1024, 0, 1) < decay.LTAU_END  # 5.2e5 us at 1 us a sample
    # lo: a window further into the buffer reads the same tau (an exponential has no origin)
    two = array("H", list(samples(100.0, 2000, 100, 16)) + list(buf))
    assert abs(decay.ltau_q16(two, 16, 64, 1600, DT) - decay.ltau_q16(buf, 0, 64, 1600, DT)) == 0


def test_a_negative_offset_is_taken_out():
    buf = samples(300.0, 2500, 0, 100)
    shifted = array("H", [min(4095, b + 60) for b in buf])  # the same decay read 60 counts high
    assert decay.ltau_q16(shifted, 0, 100, 60 * 16, DT) == decay.ltau_q16(buf, 0, 100, 0, DT)
    low = array("H", [b - 40 for b in buf[:90]])  # read 40 counts low (offset -40; every sample >= 1372)
    assert decay.ltau_q16(low, 0, 90, -40 * 16, DT) == decay.ltau_q16(buf, 0, 90, 0, DT)


DRIVER = """
import sys, json, micropython
sys.path.insert(0, '')
from array import array
import decay
cases = json.loads(sys.stdin.read())
out = []
for buf, lo, n, off, dt in cases:
    out.append(decay.ltau_q16(array('H', buf), lo, n, off, dt))
b = array('H', cases[0][0])
lo, n, off, dt = cases[0][1:]
def f(k):
    r = 0
    for _ in range(k):
        r = decay.ltau_q16(b, lo, n, off, dt)
    return r
r, err = under_heap_lock(f, 50)
print(json.dumps([out, r, err is None]))
"""


def test_bit_identical_in_the_micropython_vm_and_allocation_free(micropython, core_mpy_dir, tmp_path):
    import random

    rng = random.Random(5)
    cases = []
    for _ in range(200):
        n = rng.randint(4, 300)
        tau = 10 ** rng.uniform(1.3, 3.7)
        off = rng.randint(-50, 300)
        noise = [rng.gauss(0, 1.5) for _ in range(n)]
        buf = samples(tau, rng.randint(100, 3800), max(off, 0), n, noise=noise)
        cases.append([list(buf), 0, n, off * 16, DT])
    cases.append([[4095] * 8 + [0] * 8, 0, 16, -800, DT])  # extremes: a full-scale window, a negative offset
    script = tmp_path / "drv.py"
    script.write_text(UNDER_HEAP_LOCK + DRIVER)
    p = run_mp(micropython, script, [core_mpy_dir], stdin=json.dumps(cases))
    assert p.returncode == 0, p.stderr[-2000:]
    got, r, no_alloc = json.loads(p.stdout.strip().splitlines()[-1])
    want = [decay.ltau_q16(array("H", c[0]), *c[1:]) for c in cases]
    assert got == want
    assert sum(1 for x in want if x > 0) > 150  # most of them readable: the comparison is not of zeros
    assert no_alloc and r == want[0]
