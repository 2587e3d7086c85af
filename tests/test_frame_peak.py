"""stim._peak_counts, the firmware's end-of-pulse voltage (viper, scanned from the
falling edge, skipping samples below the best so far): the largest min of two
neighbouring samples of the board's window. Run in the MicroPython VM on
hypothesis' windows (random, few levels, rising then falling like a pulse, with
single-sample spikes and dropouts, 0/4095 rails, at any offset in the buffer),
against the reference below; the spike guard and the end-of-pulse read are
properties of the reference, checked here on every window hypothesis draws."""

import json
import textwrap

from hypothesis import given, settings
from hypothesis import strategies as st

from fw_harness import run_fw

ADC = st.integers(0, 4095)
W = 32  # board_config.ADC_WINDOW


def reference(v, lo, hi):
    """The largest min(v[k - 1], v[k]) over lo < k < hi; one sample: that one; none: 0."""
    if hi - lo < 1:
        return 0
    if hi - lo == 1:
        return v[lo]
    return max(min(v[k - 1], v[k]) for k in range(lo + 1, hi))


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
    assert res[0]["got"] == [reference(v, lo, hi) for v, lo, hi in cases]


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
    assert res[0]["got"] == [reference(v, lo, 8) for v, lo in cases]


@settings(max_examples=500, deadline=None)
@given(pulses(), st.data())
def test_one_wild_sample_never_reads_above_the_genuine_samples(p, data):
    """Safety: a wild sample (any value, anywhere in the window) can never make the read
    exceed the largest genuine sample of the pulse: Vp, hence Rp, never reads higher than
    the electrode really went, and a high Rp is what raises the charge (mQ ~ Q / Rp)."""
    v, lo, hi, _edge = p
    k = data.draw(st.integers(lo, hi - 1))
    bad = list(v)
    bad[k] = data.draw(ADC)
    genuine = [v[j] for j in range(lo, hi) if j != k]
    if genuine:
        assert reference(bad, lo, hi) <= max(genuine)


@settings(max_examples=300, deadline=None)
@given(pulses(), st.data())
def test_a_low_sample_can_only_lower_the_read(p, data):
    v, lo, hi, _edge = p
    k = data.draw(st.integers(lo, hi - 1))
    low = list(v)
    low[k] = data.draw(st.integers(0, v[k]))
    assert reference(low, lo, hi) <= reference(v, lo, hi)


@settings(max_examples=300, deadline=None)
@given(pulses())
def test_a_clean_pulse_reads_one_of_its_last_two_samples(p):
    """Rising to the fall, lower after it: the read is the second-last sample before the fall or
    later (2-4 us before the fall at 2 us sampling), never earlier."""
    v, lo, hi, edge = p
    if edge - lo >= 2 and all(v[k] >= v[k - 1] for k in range(lo + 1, edge)):
        assert reference(v, lo, hi) >= v[edge - 2]
