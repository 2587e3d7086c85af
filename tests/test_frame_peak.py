"""stim._peak_counts, the firmware's end-of-pulse voltage (viper): the larger of the
largest min of two neighbouring samples of the board's window and the last sample
before the largest drop (the falling edge), capped at its predecessor + 8 counts +
1/64. Run in the MicroPython VM on hypothesis' windows (random, few levels, rising
then falling like a pulse, with single-sample spikes and dropouts, 0/4095 rails, at
any offset in the buffer), against the reference below; the spike guard and the
end-of-pulse read are properties of the reference, checked on every window drawn."""

import json
import textwrap

from hypothesis import given, settings
from hypothesis import strategies as st

from fw_harness import run_fw

ADC = st.integers(0, 4095)
W = 32  # a window (board_config.ADC_WINDOW is 128: the same code, more samples after the fall)


def reference(v, lo, hi):
    """The larger of max(min(v[k - 1], v[k]) for lo < k < hi) and v[e - 1] capped at
    v[e - 2] + 8 + v[e - 2] // 64, e the latest k of the largest drop v[k - 1] - v[k]
    (when e - 2 >= lo); one sample: that one; none: 0."""
    if hi - lo < 1:
        return 0
    if hi - lo == 1:
        return v[lo]
    best = max(min(v[k - 1], v[k]) for k in range(lo + 1, hi))
    e = max(range(lo + 1, hi), key=lambda k: (v[k - 1] - v[k], k))
    if e - 1 > lo:
        y = v[e - 2]
        best = max(best, min(v[e - 1], y + 8 + (y >> 6)))
    return best


def packed(v, lo, hi):
    """What _peak_counts returns: reference() | e << 16, e the latest k of the largest drop (the first
    sample after the fall: the monitor's decay follows it, stim._measure); hi for fewer than 2 samples."""
    if hi - lo < 2:
        return reference(v, lo, hi) | (hi << 16)
    return reference(v, lo, hi) | (max(range(lo + 1, hi), key=lambda k: (v[k - 1] - v[k], k)) << 16)


def bound(g):
    """What one wild sample can lift the read to, at most: the largest genuine sample g + 8 + g // 64."""
    return g + 8 + (g >> 6)


@st.composite
def pulses(draw):
    """A window of W samples whose last n hold a pulse's end: rising (a charging
    electrode plus noise), then after the fall lower (the skin's discharge)."""
    n = draw(st.integers(2, W))
    pre = draw(st.integers(1, n))  # samples before the fall
    step = draw(st.integers(0, 60))
    base = draw(st.integers(0, 2000))
    noise = draw(st.lists(st.integers(0, 6), min_size=n, max_size=n))
    rise = [min(4095, base + k * step + noise[k]) for k in range(pre)]
    drop = draw(st.integers(1, 2000))
    after = [max(0, rise[-1] - drop - 3 * k + noise[pre + k]) for k in range(n - pre)]
    stale = draw(st.lists(ADC, min_size=W - n, max_size=W - n))  # the ring's older contents: never read
    return stale + rise + after, W - n, W, W - n + pre  # values, lo, hi, index of the first sample after the fall


@st.composite
def windows(draw):
    n = draw(st.integers(0, W))
    kind = draw(st.sampled_from(["random", "few"]))
    levels = ADC if kind == "random" else st.sampled_from([0, 1, 2, 4095])
    v = draw(st.lists(levels, min_size=W, max_size=W))
    return v, W - n, W


def test_peak_counts_is_the_reference_in_the_vm():
    """400 windows of each kind, through the viper code in the MicroPython VM."""
    cases = []

    @settings(max_examples=400, database=None)
    @given(st.one_of(windows(), pulses().map(lambda p: p[:3])))
    def collect(c):
        cases.append(c)

    collect()
    _, res, _ = run_fw(f"""
        from array import array
        cases = json.loads({json.dumps(json.dumps(cases))})
        result(got=[stim._peak_counts(array('H', v), lo, hi) for v, lo, hi in cases])
    """)
    assert res[0]["got"] == [packed(v, lo, hi) for v, lo, hi in cases]


def short_windows():
    """Every window of 1..6 samples over the levels 0, 1, 2, 4095, at the end of 8 samples of 7
    (5460 cases); the same loop runs in the VM (a list this long does not fit a command line)."""
    lv = [0, 1, 2, 4095]
    out = []
    for n in range(1, 7):
        for code in range(4 ** n):
            v = [7] * 8
            for j in range(n):
                v[8 - n + j] = lv[(code >> (2 * j)) & 3]
            out.append((v, 8 - n))
    return out


def test_peak_counts_on_every_short_window_over_four_levels():
    import inspect

    src = inspect.getsource(short_windows)
    _, res, _ = run_fw(f"""
        from array import array
{textwrap.indent(src, "        ")}
        result(got=[stim._peak_counts(array('H', v), lo, 8) for v, lo in short_windows()])
    """)
    cases = short_windows()
    assert len(cases) == 5460
    assert res[0]["got"] == [packed(v, lo, 8) for v, lo in cases]


@settings(max_examples=500, deadline=None)
@given(pulses(), st.data())
def test_one_wild_sample_never_reads_far_above_the_genuine_samples(p, data):
    """Safety: a wild sample (any value, high or low, anywhere in the window) can never make
    the read exceed the largest genuine sample of the pulse by more than 8 counts + 1/64:
    Vp, hence Rp, never reads much higher than the electrode really went (a high Rp is what
    raises the charge: mQ ~ Q / (Rp - x*)); the pair-min half alone never exceeds it at all."""
    v, lo, hi, _edge = p
    k = data.draw(st.integers(lo, hi - 1))
    bad = list(v)
    bad[k] = data.draw(ADC)
    genuine = [v[j] for j in range(lo, hi) if j != k]
    if genuine:
        g = max(genuine)
        assert reference(bad, lo, hi) <= bound(g)
        if hi - lo >= 2:
            assert max(min(bad[j - 1], bad[j]) for j in range(lo + 1, hi)) <= g


@settings(max_examples=300, deadline=None)
@given(pulses())
def test_a_clean_pulse_reads_its_last_sample_or_the_one_before(p):
    """Rising to the fall, lower after it: the read is never below the second-last sample
    before the fall (2-4 us early), and where the fall is the largest drop and the last
    rise is within the allowance it is the last sample before the fall (0-2 us early)."""
    v, lo, hi, edge = p
    if edge - lo >= 2 and all(v[k] >= v[k - 1] for k in range(lo + 1, edge)):
        got = reference(v, lo, hi)
        assert got >= v[edge - 2]
        drops = [v[k - 1] - v[k] for k in range(lo + 1, hi)]
        if edge < hi and v[edge - 1] - v[edge] > max(d for j, d in enumerate(drops) if lo + 1 + j != edge):
            if v[edge - 1] <= bound(v[edge - 2]):
                assert got == v[edge - 1]


def test_measure_gives_the_cores_rp_from_vp():
    """stim._measure computes Rp inline (a call is ~11 us on the chip); it must equal the core's
    sc.rp_from_vp(Vp, delivered current) for every count, monitor scale and current, the
    electrode-off value past VP_LIMIT_MV included, and 0 when no pulse was delivered."""
    cases = []

    @settings(max_examples=300, database=None)
    @given(ADC, st.one_of(st.integers(1, 262143), st.sampled_from([244141, 250000, 262143])),
           st.one_of(st.integers(0, 12000), st.sampled_from([0, 1, 2, 3])))
    def collect(x, uv, di):
        cases.append((x, uv, di))

    collect()
    import re
    from conftest import FIRMWARE
    uv_word = int(re.search(r"^_UV = const\((\d+)\)", (FIRMWARE / "stim.py").read_text(), re.M).group(1))
    cases += [(4095, 262143, 1), (4095, 262143, 10000), (4095, 244141, 7), (1, 1, 1), (0, 5, 3),
              (4000, 250000, 9999), (4000, 250000, 1)]  # Vp exactly VP_LIMIT_MV: still a resistance
    _, res, _ = run_fw(f"""
        cases = json.loads({json.dumps(json.dumps(cases))})
        s, board, usb, clock = make('steady', 1)
        c = s.chans[0]
        w = len(c.adc)
        got = []
        for x, uv, di in cases:
            for k in range(w):
                c.adc[k] = x
            c.n_samples = w
            c.v[{uv_word}] = uv  # stim._UV (a const: not an attribute)
            c.vmon_k = 0
            c.di = di
            s._measure(c)
            got.append((c.vp, c.rp, sc.rp_from_vp(c.vp, di) if di > 0 else 0))
        result(got=got)
    """)
    got = res[0]["got"]
    assert len(got) == len(cases)
    assert all(rp == want for _, rp, want in got), [g for g in got if g[1] != g[2]][:5]
    assert any(vp > 1000000 for vp, _, _ in got)  # the electrode-off value was reached
    assert any(vp == 1000000 for vp, _, _ in got)  # and the limit itself
