"""Behaviour of the controller modes on the simulated electrode (bench/controllers.py's harness)."""

import importlib.util
import sys

import sensation_core as sc

from conftest import ROOT

spec = importlib.util.spec_from_file_location("bench_controllers", ROOT / "bench" / "controllers.py")
bench = importlib.util.module_from_spec(spec)
sys.modules["bench_controllers"] = bench  # dataclasses look their module up
spec.loader.exec_module(bench)


def settle(mode, name):
    ev, n = bench.scenario_events(name)
    rows, target, me = bench.run(mode, ev, n)
    return bench.metrics(rows, target, me, ev, n)


def test_papers_mode_needs_several_pulses_after_a_gel_drop():
    """The paper: 9 pulses after a > 20 kohm drop from gel; the simulator: the same order."""
    m = settle(sc.MODE_AKHTAR, "gel-step")
    assert 4 <= m["settle"][0] <= 14


def test_fast_mode_settles_faster_than_the_paper_and_does_not_overshoot():
    for name in ("gel-step", "peel"):
        a, f = settle(sc.MODE_AKHTAR, name), settle(sc.MODE_FAST, name)
        for sa, sf in zip(a["settle"], f["settle"]):
            if sa is not None:
                assert sf is not None and sf <= sa
        assert f["over_i"] <= 0.05 and f["over_q"] <= 0.05
        assert f["rms_q"] <= a["rms_q"] + 1e-9


def test_baselines_do_not_hold_mq():
    for mode in (sc.MODE_OPEN_LOOP, sc.MODE_CONSTANT_CHARGE, sc.MODE_CONSTANT_ENERGY, sc.MODE_PULSE_WIDTH_LINEAR):
        m = settle(mode, "gel-step")
        assert m["settle"][0] is None and m["rms_q"] > 0.5
