"""stim._peak3 (viper, scanned from the falling edge, skipping samples below the
best so far) is the largest median of 3 neighbouring samples, run in the
MicroPython VM on hypothesis' captures: random, flat, rising like a charging
electrode, with single-sample spikes and 0/4095 rails."""

import json

from hypothesis import given, settings
from hypothesis import strategies as st

from fw_harness import run_fw

ADC = st.integers(0, 4095)


@st.composite
def captures(draw):
    n = draw(st.integers(3, 120))
    kind = draw(st.sampled_from(["random", "few", "rising"]))
    if kind == "random":
        v = draw(st.lists(ADC, min_size=n, max_size=n))
    elif kind == "few":
        v = draw(st.lists(st.sampled_from([0, 1, 2, 4095]), min_size=n, max_size=n))
    else:
        step = draw(st.integers(0, 60))
        noise = draw(st.lists(st.integers(0, 40), min_size=n, max_size=n))
        v = [min(4095, k * step + e) for k, e in enumerate(noise)]
        for k in draw(st.lists(st.integers(0, n - 1), max_size=3)):
            v[k] = draw(ADC)  # spikes and dropouts
    return v


def reference(v):
    return max(sorted(v[k - 2:k + 1])[1] for k in range(2, len(v)))


@settings(max_examples=1)
@given(st.lists(captures(), min_size=400, max_size=400))
def test_peak3_is_the_largest_median_of_3(cases):
    _, res, _ = run_fw(f"""
        from array import array
        cases = json.loads({json.dumps(json.dumps(cases))})
        result(got=[stim._peak3(array('H', v), len(v)) for v in cases])
    """)
    assert res[0]["got"] == [reference(v) for v in cases]


def test_peak3_on_every_short_capture_over_four_levels():
    """Exhaustive: every capture of 3..6 samples over the levels 0, 1, 2, 4095 (5440 cases)."""
    import itertools

    cases = [list(v) for n in range(3, 7) for v in itertools.product([0, 1, 2, 4095], repeat=n)]
    _, res, _ = run_fw(f"""
        from array import array
        cases = json.loads({json.dumps(json.dumps(cases))})
        result(got=[stim._peak3(array('H', v), len(v)) for v in cases])
    """)
    assert res[0]["got"] == [reference(v) for v in cases]
