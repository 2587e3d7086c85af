"""Behaviour of the controller modes on the simulated electrode (bench/controllers.py's harness)."""

import importlib.util
import sys

import pytest

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


@pytest.mark.parametrize("fast", [sc.MODE_FAST, bench.FAST_NO_MODEL])
def test_fast_mode_settles_faster_than_the_paper_and_does_not_overshoot(fast):
    """With and without the skin model."""
    for name in ("gel-step", "peel"):
        a, f = settle(sc.MODE_AKHTAR, name), settle(fast, name)
        for sa, sf in zip(a["settle"], f["settle"]):
            if sa is not None:
                assert sf is not None and sf <= sa
        assert f["over_i"] <= 0.05 and f["over_q"] <= 0.05
        assert f["rms_q"] <= a["rms_q"] + 1e-9


def step_cases():
    for i0 in (700, 1000, 2000):
        for d in (-30, -20, -10, 10, 20):  # (+50 kohm: past 200 kohm for every controller, the oracle too)
            if bench.Electrode().rp_kohm(i0, 1000) + d >= 3:
                yield i0, d


def test_fast_mode_with_the_skin_model_settles_within_2_pulses_after_every_step():
    """The issue's target: every step disturbance of the benchmark (gel on/off, peel 25/50/75 %
    and back, steps of -30...+20 kohm from three operating points) settles within 2 pulses,
    with the model fitted to the calibration's pulses (host/skin.py), not given."""
    for name in ("gel-step", "peel"):
        f = settle(sc.MODE_FAST, name)
        assert all(s is not None and s <= 2 for s in f["settle"]), (name, f["settle"])
    for i0, d in step_cases():
        ev, n = bench.step_events(i0, d)
        f = bench.metrics(*bench.run(sc.MODE_FAST, ev, n, i0=i0), ev, n)
        assert all(s is not None and s <= 2 for s in f["settle"]), (i0, d, f["settle"])
        assert f["over_i"] <= 0.05 and f["over_q"] <= 0.05, (i0, d)


def test_fast_mode_with_a_noisy_skin_model_stays_safe():
    """0.3 % Rp noise on every pulse, the calibration's pulses included (so the fitted model is
    off too): no overshoot beyond 5 % and an mQ RMS within 0.1 % of mQ of the paper's mode."""
    for i0, d in [(1000, -20), (1000, 10), (2000, 20), (700, -30)]:
        ev, n = bench.step_events(i0, d)
        a = bench.metrics(*bench.run(sc.MODE_AKHTAR, ev, n, i0=i0, noise=0.003), ev, n)
        f = bench.metrics(*bench.run(sc.MODE_FAST, ev, n, i0=i0, noise=0.003), ev, n)
        assert f["over_i"] <= 0.05 and f["over_q"] <= 0.05, (i0, d, f)
        assert f["rms_q"] <= a["rms_q"] + 1e-3, (i0, d, f["rms_q"], a["rms_q"])


def test_baselines_do_not_hold_mq():
    for mode in (sc.MODE_OPEN_LOOP, sc.MODE_CONSTANT_CHARGE, sc.MODE_CONSTANT_ENERGY, sc.MODE_PULSE_WIDTH_LINEAR):
        m = settle(mode, "gel-step")
        assert m["settle"][0] is None and m["rms_q"] > 0.5


def test_the_laws_own_point_after_a_75_percent_peel_is_beyond_t_max():
    """Why the firmware's peel test holds mQ after 25/50 % and re-applying but not 75 %:
    the self-consistent pulse of the paper's law on that skin needs T > 8 ms (the
    board's hard limit). Solved on the simulated skin itself, not on the controller."""
    c = sc.Controller(*bench.LIMITS)
    e = bench.Electrode()
    c.calibrate(1000, 1000, round(e.rp_kohm(1000, 1000) * 1000), bench.X, bench.Y)
    me = 1000 * 1000 * 1000
    t_needed = {}
    for contact in (1.0, 0.75, 0.5, 0.25):
        e.contact = contact
        q = bench.oracle_charge(c, e, 1_000_000)
        t_needed[contact] = q * q / me
    assert abs(t_needed[1.0] - 1000) < 5
    assert t_needed[0.75] < t_needed[0.5] < 8000 < t_needed[0.25], t_needed


def test_fast_mode_never_overshoots_on_any_benchmark_case():
    """<= 5 % beyond the range before/after (the issue's shock-risk bound), on every case,
    and never a worse mQ RMS than the paper's mode by more than 0.1 % of mQ."""
    for name in ("gel-step", "gel", "peel"):
        ev, n = bench.scenario_events(name)
        a = bench.metrics(*bench.run(sc.MODE_AKHTAR, ev, n), ev, n)
        f = bench.metrics(*bench.run(sc.MODE_FAST, ev, n), ev, n)
        assert f["over_i"] <= 0.05 and f["over_q"] <= 0.05, name
        assert f["rms_q"] <= a["rms_q"] + 1e-3, name
    for i0 in (700, 1000, 2000):
        for d in (-30, -20, -10, 10, 20, 50):
            if bench.Electrode().rp_kohm(i0, 1000) + d < 3:
                continue
            ev, n = bench.step_events(i0, d)
            ra, rf = bench.run(sc.MODE_AKHTAR, ev, n, i0=i0), bench.run(sc.MODE_FAST, ev, n, i0=i0)
            a, f = bench.metrics(*ra, ev, n), bench.metrics(*rf, ev, n)
            assert f["over_i"] <= 0.05 and f["over_q"] <= 0.05, (i0, d)
            if ra[0][-1, 1] > 0 and rf[0][-1, 1] > 0:  # (+50 kohm @ 1 mA: Rp passes 200 kohm, both stop)
                assert f["rms_q"] <= a["rms_q"] + 1e-3, (i0, d, f["rms_q"], a["rms_q"])


@pytest.mark.parametrize("name", ["exercise", "gel"])
def test_fast_mode_halves_the_papers_error_under_a_drift(name):
    """Exercise (5 min of sweating, 10 min rest) and gel soaking in (tau 1 s, then drying,
    tau 2 s): the paper's iteration lags the drift and rounds I and T separately; FAST's
    Newton step, charge-exact pulse and falling-drift prediction halve its mQ RMS."""
    ev, n = bench.scenario_events(name)
    a = bench.metrics(*bench.run(sc.MODE_AKHTAR, ev, n), ev, n)
    f = bench.metrics(*bench.run(sc.MODE_FAST, ev, n), ev, n)
    assert f["rms_q"] <= a["rms_q"] / 2, (f["rms_q"], a["rms_q"])
    assert f["over_i"] <= 0.05 and f["over_q"] <= 0.05


def test_repeated_sweeps_fit_reports_its_uncertainty_and_refuses_a_model_it_cannot_trust():
    import numpy as np
    from steadytouch import skin

    e = bench.Electrode()
    rng = np.random.default_rng(1)
    pts = skin.sweep_wide(1000, 1000)

    def sweeps(n, noise):
        return [[(i, t, round(e.rp_kohm(i, t) * 1000 * (1 + noise * rng.normal()))) for i, t in pts] for _ in range(n)]

    good = skin.fit_sweeps(sweeps(5, 0.003), 1000, 1000)
    assert good.trusted and good.shape_sd < skin.TRUST_SHAPE_SD and good.args() == good.model.args()
    bad = skin.fit_sweeps(sweeps(5, 0.05), 1000, 1000)  # 5 % noise: the shape is not known
    assert not bad.trusted and bad.shape_sd > skin.TRUST_SHAPE_SD and bad.args() == (0, 0, 0)
    assert "known only to" in bad.why
    assert not skin.fit_sweeps(sweeps(2, 0.0), 1000, 1000).trusted  # 2 sweeps cannot tell their spread


def test_on_the_realistic_board_no_step_surges_after_the_first_correction():
    """Issue 13, deliverable 5 on 16 unseen electrodes read through the realistic board (with
    the self-test correction and the chip's capture and end-of-pulse read): with the averaged,
    trusted model and without a model, no step has a felt mQ more than 5 % above its target
    after the first corrected pulse (before the stretched secant on a step down: 3 and 10 such
    steps here, up to +29 %; over 30 electrodes, 105 steps: 7 and 20 -> 0 and 0,
    docs/performance.md, which also has its cost: a current above the settled one on more
    steps). Every step gets within 1 % of the felt target, and the controller reaches 1 % of
    its measured target in a median of <= 2 pulses with the model. (The goal's 90th
    percentile of 2 pulses to 1 % of the felt target does not hold yet: 6 here, 5 before.)"""
    res, trust, _ = bench.study(16, "real", 10, True)
    avg, free = res["fast, averaged sweeps + trust"], res["fast, no model"]
    assert max(avg["surge"]) <= 0.05, max(avg["surge"])
    assert max(free["surge"]) <= 0.05, max(free["surge"])
    assert max(avg["settle"]) < 10**6 and max(free["settle"]) < 10**6  # every step within 1 % of the felt target
    assert sorted(avg["seen"])[len(avg["seen"]) // 2] <= 2  # median pulses to 1 % of the measured target
    # the rises' first corrected pulse (gel off, a peel: pulse 0 below target, pulse 1 the controller's own
    # choice) is not above target by more than 5 % with the averaged model or none, nor by more than 10 % with
    # one sweep sent as is (+5.2 % here): before session 17's fresh-rise test the averaged model's went up to
    # +107 % here, the one-sweep model's to +32 % (checked on the core before it)
    for name, bound in (("fast, averaged sweeps + trust", 0.05), ("fast, 1 sweep (sent as is)", 0.10),
                        ("fast, no model", 0.05)):
        assert max(res[name]["rise1"]) <= bound, (name, max(res[name]["rise1"]))


def test_bench_supervisor_is_the_firmwares_raise_rule():
    """bench.Supervisor as firmware/stim.py's _control: a lower charge at once, a raise held
    one pulse, then the smaller of the two proposals in a row, not past the pulse before a fall
    of more than 1/32 within 16 pulses of it until that pulse is sent again; a stop at once."""
    s = bench.Supervisor(1000, 1000)
    # each proposal with its own status bits (1..10): the pulse sent carries the status of the proposal it is
    # (the controller is told it before the next update, as stim._control does)
    seq = [((990, 1000, 1), (990, 1000, 1)),  # lower by 1 % (< 1/32): sent at once, no hold after it
           ((1200, 1000, 2), (990, 1000, 1)),  # raise: held, the pulse before again
           ((1100, 1000, 3), (1100, 1000, 3)),  # second raise in a row: the smaller of the two
           ((1000, 1000, 4), (1000, 1000, 4)),  # lower by 9 % (> 1/32): at once; no raise past 1100 x 1000 now
           ((1000, 1300, 5), (1000, 1000, 4)),  # raise: held
           ((1500, 1000, 6), (1100, 1000, 3)),  # the smaller of two is 1000 x 1300, past the pulse before the fall
           ((1300, 1000, 7), (1100, 1000, 3)),  # back at that pulse: the hold ends; this raise is held
           ((1250, 1000, 8), (1250, 1000, 8)),  # the smaller of two in a row, both read on it
           ((1300, 1000, 9), (1250, 1000, 8)),  # raise: held
           ((1400, 1000, 10), (1300, 1000, 9)),  # the held proposal is the smaller: it is sent, with its status
           ((0, 0, 0), (0, 0, 0))]  # stopped
    for prop, sent in seq:
        s.propose(*prop)
        assert (s.i_ua, s.t_us, s.s) == sent, (prop, sent)


def test_bench_run_through_the_supervisor_raises_only_after_a_held_pulse():
    """With supervisor=True every raise of the charge follows a pulse repeated (held); the
    controller alone raises without (so the check can fail)."""
    ev, n = bench.scenario_events("gel-step")
    for sup in (True, False):
        rows, _, _ = bench.run(sc.MODE_FAST, ev, n, supervisor=sup)
        q = rows[:, 1] * rows[:, 2]
        raises = [k for k in range(2, len(rows)) if q[k] > q[k - 1] > 0]
        unheld = [k for k in raises if (rows[k - 1, 1], rows[k - 1, 2]) != (rows[k - 2, 1], rows[k - 2, 2])]
        assert raises
        assert (not unheld) if sup else unheld, (sup, unheld[:5])


def test_through_the_firmwares_supervisor_no_step_surges_after_the_first_correction(monkeypatch):
    """The same 16 electrodes as the board delivers them: the firmware's raise rule between the
    controller and the realistic board (bench.Supervisor: a raise held one pulse, then the
    smaller of two proposals). With the averaged, trusted model and without a model no step
    is felt more than 5 % above target after the first corrected pulse, and every step gets
    within 1 % (docs/performance.md, "Through the firmware's supervisor": a held pulse per
    raise makes the rises slower, not higher; a change that made the pair's two proposals
    agree raised single-read overshoots there, session 21)."""
    monkeypatch.setattr(bench, "SUPERVISOR", True)
    res, _, _ = bench.study(16, "real", 10, True)
    avg, free = res["fast, averaged sweeps + trust"], res["fast, no model"]
    assert max(avg["surge"]) <= 0.05, max(avg["surge"])
    assert max(free["surge"]) <= 0.05, max(free["surge"])
    # within 1 % as the controller measures it; felt, the DAC's gain error (0.994 on channel 0), which the
    # self-test on a resistor cannot part from the monitor's, holds 2 of the 64 steps at -1.2 % (mQ's y*
    # magnifies it as the charge moves from calibration: docs/performance.md, "MODE_FAST reads tau") ...
    assert max(avg["seen"]) < 10**6 and max(free["seen"]) < 10**6
    # ... and with the DAC's gain exact every step is felt within 1 % too
    monkeypatch.setattr(bench.board_sim, "DAC_GAIN", (1.0, 1.0, 1.0, 1.0))
    res, _, _ = bench.study(16, "real", 10, True)
    avg, free = res["fast, averaged sweeps + trust"], res["fast, no model"]
    assert max(avg["settle"]) < 10**6 and max(free["settle"]) < 10**6
    assert max(avg["surge"]) <= 0.05 and max(free["surge"]) <= 0.05
    held = bench.run(sc.MODE_FAST, bench.STUDY_EVENTS, 200)[0]  # (the switch is live: raises follow a repeat)
    q = held[:, 1] * held[:, 2]
    assert all((held[k - 1, 1], held[k - 1, 2]) == (held[k - 2, 1], held[k - 2, 2])
               for k in range(2, len(held)) if q[k] > q[k - 1] > 0)
