"""MODE_FAST's skin-model rules (docs/controller.md, "MODE_FAST with a skin model") checked on
closed loops: rule 5's cap on a rise and rule 4's refit fall-back."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

import sensation_core as sc

from conftest import ROOT

spec = importlib.util.spec_from_file_location("bench_controllers", ROOT / "bench" / "controllers.py")
bench = sys.modules.get("bench_controllers")
if bench is None:
    bench = importlib.util.module_from_spec(spec)
    sys.modules["bench_controllers"] = bench  # dataclasses look their module up
    spec.loader.exec_module(bench)

# Closed loops of a random review (session 14) where the model's first rise after a large
# step of Rp was above 16 paper steps while the paper's step was >= 2**22 (1/16 pC): rule 5's
# cap was skipped there (up to 23.5 paper steps: 0.75 -> 7.6 uC in one pulse). Each line:
# the update index that broke it, then limits (5), calibration (5), mode, skin (3), the Rp read
# before every update.
CASES = [line.split() for line in (Path(__file__).parent / "golden" / "rule5_cases.txt").read_text().splitlines() if line]


def study_run(seed, k, board="real", sweeps=10, scope=False):
    """bench.study's closed loop for its electrode k of this seed, MODE_FAST with the averaged
    model (10 sweeps; the self-test correction on the realistic board, with scope the DAC gain
    too): (rows, felt target)."""
    rng = np.random.default_rng(seed)
    for _ in range(k + 1):
        mk = bench.random_electrode(rng)
    corr = bench.selftest_correction(board, scope=scope)
    rows, target, _ = bench.run(sc.MODE_FAST, bench.STUDY_EVENTS, bench.STUDY_N, i0=1000, board=board, sweeps=sweeps,
                                electrode=mk, correction=corr, seed=1000 + k)
    assert bench.FIT_INFO.get("trusted"), bench.FIT_INFO
    return rows, target


def _largest_rise(case):
    """One of the review's loops through the core: the largest model rise in paper steps, each
    checked against rule 5's cap."""
    v = [int(w) for w in case[1:]]
    c = sc.Controller(*v[0:5])
    c.calibrate(*v[5:10])
    c.set_mode(v[10])
    c.set_skin(*v[11:14])
    worst = 0.0
    for rp in v[14:]:
        i_k, t_k = c.i_ua, c.t_us
        q_k = i_k * t_k
        step = (c._line(rp) >> 4) - q_k  # the paper's step (drift only lowers it: a looser bound)
        c.update(rp)
        q = c.i_ua * c.t_us
        if step > 0 and q > q_k:
            # 2**FAST_MODEL_RAISE_LOG2 paper steps, within the pulse's resolution (1 uA, 1 us)
            assert q - q_k <= 16 * step + c.i_ua + c.t_us, (i_k, t_k, rp, c.i_ua, c.t_us, (q - q_k) / step)
            worst = max(worst, (q - q_k) / step)
    return worst


@pytest.mark.parametrize("case", CASES, ids=[f"update {c[0]}" for c in CASES])
def test_a_model_rise_is_at_most_16_paper_steps_even_when_the_step_is_large(case):
    _largest_rise(case)


def test_the_review_loops_reach_the_caps_range():
    # they can fail the cap only if they rise by more than 8 paper steps somewhere: three of the four
    # still do (16.1, 16.1, 16.0 paper steps: the cap within the pulse's resolution); the loop of
    # update 186 did too until rule 4 refitted Cp only on a move of I by 1/8 octave or more
    # (session 29; before, 1/32): it now rises by 2.7 paper steps at most
    rises = sorted(_largest_rise(c) for c in CASES)
    assert len(rises) == 4 and rises[1] > 8, rises


def test_gel_coming_off_is_not_left_to_the_model_free_creep():
    """Rule 4's fall-back: issue 13's study, electrode 5 (seed 7), gel off on the realistic
    board with the averaged, trusted model. A two-pulse refit had moved Cp up 0.4 octave on
    reads 1-2 % off; the law had no root on that model, and every later pulse took the
    model-free step: 9 pulses to 1 % of the felt target. With the fitted Cp back: 3; since
    session 17's fresh-rise test (rules 3 and 6 after a reading that missed a checked model by
    more than Rp/8) the first corrected pulse takes the contact hypothesis's smaller charge
    (-10 % instead of -6 % of the target), and the model reaches 1 % on pulse 4: the price of
    no longer overshooting after a peel (docs/controller.md, rule 3)."""
    rows, target = study_run(7, 5)
    reach, surge, _ = bench.within(rows, target, bench.STUDY_EVENTS, bench.STUDY_N, 0.01)
    assert bench.STEP_NAMES[1].startswith("gel off")
    assert reach[1] is not None and reach[1] <= 4, reach
    assert surge[1] <= 0.05, surge


def test_a_law_that_crosses_twice_takes_the_nearest_fixed_point_in_the_steps_direction():
    """Rule 2's nearest root: issue 13's study, electrode 3 (seed 7), gel off, on the exact
    bench (no read error) with the averaged, trusted model. Along this electrode's mE curve
    the felt mQ is within 2.5 % of its target from T = 235 to 3000 us: the law crosses the line
    at T ~ 245 us (stable) and again at the calibration pulse (T = 1000 us, unstable), so from
    the pulse at T = 104 us both ends of the search (Q_k/4, 4 Q_k) ask for more charge and the
    search found no root: every later pulse took the model-free step and crept (7 pulses to
    1 %). The nearest fixed point in the paper's direction: 2."""
    rows, target = study_run(7, 3, "exact")
    reach, surge, _ = bench.within(rows, target, bench.STUDY_EVENTS, bench.STUDY_N, 0.01)
    assert bench.STEP_NAMES[1].startswith("gel off")
    a = bench.STUDY_EVENTS[1].pulse
    assert rows[a, 2] < 120, rows[a]  # the step starts from a short pulse (T ~ 104 us) ...
    assert 200 <= rows[a + 2, 2] <= 300, rows[a:a + 3]  # ... and lands near the stable fixed point, not at 1000 us
    assert reach[1] is not None and reach[1] <= 2, reach
    assert max(surge) <= 0.05, surge


def test_a_peel_after_a_checked_model_is_a_fresh_rise():
    """Rules 3 and 6 after a step that a checked model did not predict: issue 13's study, seed 11,
    electrode 25, half peeled, realistic board, averaged and trusted model. The pulse before the
    peel was a model jump (in steady state the model jumps by small amounts), so the rise after
    the peel was not 'fresh': the hydration hypothesis alone, no halving into the ceiling, and
    the first corrected pulse was felt 108 % above target. A reading that misses the model's
    prediction by more than Rp/8 now makes the next jump a fresh one: the contact hypothesis's
    smaller charge. Over 11 seeds x 30 electrodes the rises' first corrected pulses above target
    by > 5 % went 81 -> 0 (docs/performance.md)."""
    rows, target = study_run(11, 25)
    assert bench.STEP_NAMES[2] == "half peeled"
    first = bench.first_rise(rows, target, bench.STUDY_EVENTS, bench.STUDY_N)
    assert first[2] is not None and first[2] <= 0.05, first
    reach, surge, _ = bench.within(rows, target, bench.STUDY_EVENTS, bench.STUDY_N, 0.01)
    assert max(surge) <= 0.05, surge
    assert all(r is not None and r <= 4 for r in reach), reach


@pytest.mark.parametrize("seed, k, before", [(13, 5, 1.308), (11, 28, 0.630)])
def test_gel_on_a_pulse_at_the_ceiling_is_met_by_the_first_corrected_pulse(seed, k, before):
    """Rule 2's fall past Q_k/4 (session 27; skin_model._law_fall): issue 13's study, realistic
    board, averaged and trusted model, gel on a pulse at or near the duration ceiling (T 3500 to
    8000 us). The law asks for Q_k/5 ... Q_k/9 there, the search from Q_k/4 found no root, the
    model-free step went instead, and the first corrected pulse was still felt 'before' above
    target (+131 %, +63 %; 44 of the study's 330 gel-on steps above +15 %). Now it is within 5 %,
    and its current within 5 % of the current the channel settles at (no dip of the charge that
    a shorter, sharper pulse would be). The settled pulse before the gel keeps its shape: on
    electrode 28 the law is nearly flat along the mE curve (a root just below Q_k/4 of a pulse
    on the line), and a version that searched Q_k/16 ... 4 Q_k at once moved it from
    535 uA x 3489 us to 2511 uA x 159 us."""
    rows, target = study_run(seed, k)
    assert bench.STEP_NAMES[0].startswith("gel on")
    a = bench.STUDY_EVENTS[0].pulse
    assert rows[a - 1, 2] >= 3000, rows[a - 1]  # the pulse before the gel: long, near the ceiling
    assert (rows[a, 4] - target) / target > 1.0, rows[a]  # the gel's first pulse, felt x 2 and more
    first = (rows[a + 1, 4] - target) / target
    assert abs(first) <= 0.05, (first, before, rows[a - 1:a + 4])
    settled = rows[a + 10, 1]
    assert rows[a + 1:a + 10, 1].max() <= 1.05 * settled, rows[a:a + 10]
    i_settle = rows[10:a, 1]
    assert i_settle.max() <= 1.25 * i_settle.min(), (i_settle.min(), i_settle.max())  # no change of shape
    reach, surge, _ = bench.within(rows, target, bench.STUDY_EVENTS, bench.STUDY_N, 0.01)
    assert reach[0] is not None and reach[0] <= 2 and surge[0] <= 0.05, (reach, surge)


def test_gel_on_at_the_ceiling_whose_model_asks_for_a_modest_fall_does_not_surge():
    """Validation seed 31, electrode 28 (30 sweeps, the DAC gain known by selftest --scope): gel on
    a pulse settled at the ceiling (461 uA x 7990 us). The paper's step at the reading asks for
    Q_k x 0.41, but the model on the mE curve asked at Q_k for a fall of only 0.73 octave (the
    curve's pulse of that charge is longer than the ceiling pulse read), so the fall past Q_k/4
    was not searched, the model-free step went (+50 % felt, the first corrected pulse), and on
    the next reading the model asked for -0.5 octave, again not searched: the model-free secant
    sent +37.7 % (a surge). Now the reading after one on which the paper's step asked for less
    than half with no model answer confirms the fall (session 28): the second corrected pulse
    is within 5 % and none after it is felt more than 5 % above target. (Session 28's first
    version, gated on the paper's step at one reading, met the first corrected pulse too, but
    one read x 0.45 then took the fall: its review.)"""
    rows, target = study_run(31, 28, sweeps=30, scope=True)
    a = bench.STUDY_EVENTS[0].pulse
    assert rows[a - 1, 2] >= 7000, rows[a - 1]  # at the ceiling before the gel
    assert (rows[a, 4] - target) / target > 1.0, rows[a]
    rel = (rows[a + 2:a + 100, 4] - target) / target
    assert abs(rel[0]) <= 0.05, rows[a - 1:a + 4]
    assert rel.max() <= 0.05, (rel.max(), rows[a - 1:a + 4])


def test_one_read_of_about_half_does_not_move_a_pulse_settled_at_the_ceiling(monkeypatch):
    """Review of session 28's first version (the fall past Q_k/4 gated on the paper's step at one
    reading): on validation seed 31, electrode 28 (30 sweeps, --scope) one Rp read x 0.45 at pulse
    30 took the fall and the settled pulse moved for good, 460 uA x 7997 us -> 2554 uA x 153 us
    (29 of 31 electrodes settled at the ceiling moved so). With the confirmation by the next
    reading the honest reading after it asks for more, and the pulse is back within 10 % by pulse
    45, nothing felt above +5 %."""
    real = sc.Controller.update
    n = [0]

    def update(self, rp_ohm):
        n[0] += 1  # (pulse k is call k + 1)
        return real(self, round(rp_ohm * 0.45) if n[0] == 31 else rp_ohm)

    monkeypatch.setattr(sc.Controller, "update", update)
    rows, target = study_run(31, 28, sweeps=30, scope=True)
    i = rows[:, 1]
    assert rows[29, 2] >= 7000, rows[29]  # settled at the ceiling
    assert abs(i[45] - i[29]) <= 0.1 * i[29], (i[29], i[30:46])
    rel = (rows[31:50, 4] - target) / target
    assert rel.max() <= 0.05, rel


@pytest.mark.parametrize("seed, k, factor", [(13, 5, 0.85), (13, 5, 0.7), (13, 5, 0.5), (11, 28, 0.85), (11, 28, 0.7)])
def test_one_low_read_does_not_move_a_pulse_settled_at_the_ceiling_for_good(monkeypatch, seed, k, factor):
    """Review of session 27 (HIGH against the first version of the fall past Q_k/4, which searched
    it when the law on the model asked at Q_k for a fall of more than 1/8): on these electrodes mQ
    is nearly flat along the mE curve and the law has a second fixed point far below the pulse
    settled at the ceiling; one Rp read 15 % low (pulse 40, no step of the skin) found it and the
    pulse stayed there, x 5 ... 8 in current (13/5: 357 uA x 7978 us -> 2399 uA x 174 us). Now the
    fall is searched only when the law asks at Q_k for less than half (or on the reading after a
    big fall the model did not answer, when the model anchored on it still asks for less): after
    such a read the current moves at most x 2 and the pulse before the gel (pulse 49) is back
    within 10 % (all five fail with the 1/8 version). Not here: 11/28 with a read x 0.5, which moves the pulse
    to the other fixed point on main too (the model-free step down, then the law's rise)."""
    real = sc.Controller.update
    n = [0]

    def update(self, rp_ohm):
        n[0] += 1  # (the study's loop: one update a pulse, pulse k is call k + 1)
        return real(self, round(rp_ohm * factor) if n[0] == 41 else rp_ohm)

    monkeypatch.setattr(sc.Controller, "update", update)
    rows, target = study_run(seed, k)
    assert n[0] > 41, n  # the read was injected inside the run
    i = rows[:, 1]
    assert rows[39, 2] >= 3000, rows[39]  # settled long, at or near the ceiling
    assert i[41:50].max() <= 2.0 * i[39], (i[39], i[41:50])
    assert abs(i[49] - i[39]) <= 0.1 * i[39], (i[39], i[49])


def test_the_nearest_fixed_point_search_stays_within_its_range(monkeypatch):
    """Review of session 17: with the measured pulse at the ceiling carrying more charge than the
    mE curve gives at t_max, _law_near's first evaluation (at Q_k) lay past its upper end: a unit
    of work spent for nothing, which could turn a later 'no answer' into a cut. Now nothing is
    evaluated there."""
    import skin_model as sm

    seen = []
    real = sm._law_near

    def spy(vv, lq_k, hi):
        w = vv[sm._V_WORK]
        r = real(vv, lq_k, hi)
        seen.append((lq_k, hi, vv[sm._V_WORK] - w, r))
        return r

    monkeypatch.setattr(sm, "_law_near", spy)
    c = sc.Controller(1, 20000, 1, 8000, 33554432)
    c.calibrate(1818, 891, 23989, -7039, 597370)
    c.set_mode(sc.MODE_FAST)
    c.set_skin(2357, 78469, 48567)
    for rp in (24216, 135965, 36390):
        c.update(rp)
    past = [s for s in seen if s[0] >= s[1]]
    assert past, seen  # the case arises ...
    assert all(s[2] == 0 and s[3] == sm.NOROOT for s in past), past  # ... and costs nothing


def peel_after_gel_off(rng, k, d):
    """Exact bench (the core alone, no read error, one fitted sweep): gel on, gel off, then half
    peeled d pulses after gel came off. The felt mQ's largest excess over target from the
    peel's first corrected pulse on (40 pulses)."""
    mk = bench.random_electrode(rng) if k is None else k
    ev = [bench.Event(50, h=0.3), bench.Event(150, h=1.0), bench.Event(150 + d, contact=0.5)]
    n = 150 + d + 60
    rows, target, _ = bench.run(sc.MODE_FAST, ev, n, electrode=mk, seed=1000)
    rel = (rows[151 + d:191 + d, 4] - target) / target
    return mk, float(np.nanmax(rel))


@pytest.mark.parametrize("d", [1, 2])
def test_a_peel_right_after_gel_off_is_no_worse_than_the_peel_alone(d):
    """Review of session 17 (HIGH): a peel 2 pulses after gel came off, on the core alone. The pulse
    before the peel was the model's check of its gel-off jump; the peel's reading missed the model
    by more than Rp/8, a two-pulse refit across the peel explained both readings with Cp up to 0.4
    octave above the calibrated one (the skin's Cp is c x contact area: a peel lowers it, hydration
    leaves it), and the hydration answer on that Cp was felt up to 258 % above target (23 of 60
    electrodes of seed 7 above 5 %). A refit above the fitted Cp (by more than 1/64 octave, the
    read's rounding) on such a miss is now refused and the jump is a fresh one (rule 3's
    contact hypothesis). A peel 1 pulse after gel off (session 18): the gel-off step's model jump ran
    out of work, so the peel's reading came after a model-free step that moved I and T, and it was
    not seen as a step: +14.4 % (electrode 1). Now a reading whose log Rp moved by more than
    |log I| + |log T| + 1/8 (what one skin allows) is a step too. Each of 30 electrodes: within 10 %
    of target, or no worse than the same peel 40 pulses after gel off."""
    rng = np.random.default_rng(7)
    bad = []
    for k in range(30):
        mk, near = peel_after_gel_off(rng, None, d)
        _, alone = peel_after_gel_off(rng, mk, 40)
        if near > 0.10 and near > alone + 0.01:
            bad.append((k, round(near, 3), round(alone, 3)))
    assert not bad, bad


def test_a_peel_alone_reaching_the_ceiling_is_not_felt_above_target():
    """A peel on a settled electrode (gel off 40 pulses before), core alone, 30 electrodes of seed 7.
    Where the law's answer is more than 4 x the measured charge the model had no answer on the
    peel's first reading (the model-free step), and the next jump was 'fresh' with the pulse before
    already on the peeled skin: the contact hypothesis found nothing to explain, the hydration
    answer on the old Cp went into the duration ceiling, and the next pulse was felt up to 37 %
    above target (electrode 5: +37 %; 3 of the first 60 above 5 %). A jump that sees such a step and gives no answer now marks its pulse,
    and the next jump refits Cp on the pair (both on the skin as it is: rule 4), Cp 1 octave down
    here. Every electrode: at most 5 % above target from the peel's first corrected pulse on."""
    rng = np.random.default_rng(7)
    worst = []
    for k in range(30):
        _, alone = peel_after_gel_off(rng, None, 40)
        worst.append(round(alone, 3))
    assert max(worst) <= 0.05, [(k, w) for k, w in enumerate(worst) if w > 0.05]


def test_entering_the_ceiling_at_a_higher_current_does_not_pass_the_fixed_point():
    """MODE_FAST without a model (issue 13's study, seed 19, electrode 24: its averaged fit is not
    trusted, so FAST runs model-free), realistic board, half peeled. The steps climb the mE curve
    to T = 7920 us; the next step enters the duration ceiling at a *higher* current (355 -> 523 uA),
    where Rp falls as the charge rises. The paper's step there was felt 38 % above target. Now a
    Newton step with the steepest fall the skin allows (Rp at most as 1/I: G >= -mQ Rp / L):
    -1.3 % on that pulse, and no pulse of the run above +5 %."""
    rng = np.random.default_rng(19)
    for _ in range(25):
        mk = bench.random_electrode(rng)
    corr = bench.selftest_correction("real")
    rows, target, _ = bench.run(sc.MODE_FAST, bench.STUDY_EVENTS, bench.STUDY_N, i0=1000, board="real", sweeps=10,
                                electrode=mk, correction=corr, seed=1000 + 24)
    assert not bench.FIT_INFO["trusted"], bench.FIT_INFO  # no model sent: MODE_FAST alone
    a = bench.STUDY_EVENTS[2].pulse
    assert bench.STEP_NAMES[2] == "half peeled"
    ceil = [p for p in range(a, a + 10) if rows[p, 2] >= 7900]
    assert ceil and rows[ceil[0] + 1, 1] > rows[ceil[0], 1], rows[a:a + 10]  # the case: into the ceiling, I rising
    reach, surge, _ = bench.within(rows, target, bench.STUDY_EVENTS, bench.STUDY_N, 0.01)
    assert max(surge) <= 0.05, surge


def test_a_step_seen_on_a_pulse_moved_a_little_is_still_a_step():
    """Issue 13's study, seed 13, electrode 1, half peeled, realistic board, averaged and trusted
    model. The peel's first reading came on a pulse 4 uA off the one before (the loop's small steps
    at steady state), so the step test on an unchanged pulse did not mark it; the model had
    no answer for three pulses and then jumped into the ceiling on the old Cp: +21.5 % felt. A pulse
    within 1/32 in log I and log T of the one before now counts as unchanged: the next jump refits
    Cp on the pair (1 octave down) and lands at -0.2 % on pulse 3."""
    rows, target = study_run(13, 1)
    assert bench.STEP_NAMES[2] == "half peeled"
    a = bench.STUDY_EVENTS[2].pulse
    assert rows[a - 1, 1] != rows[a, 1], rows[a - 1:a + 1]  # the case: the pulse moved a little
    reach, surge, _ = bench.within(rows, target, bench.STUDY_EVENTS, bench.STUDY_N, 0.01)
    assert max(surge) <= 0.05, surge
    assert reach[2] is not None and reach[2] <= 3, reach


def exact_run_with_a_bad_read(k_seed, k, bad_pulse, factor, n=270, events=None):
    """bench.run's exact bench (one fitted sweep, MODE_FAST, the study's steps or the events given)
    on electrode k of the seed, with the Rp read on one pulse off by factor: the felt mQ's largest
    excess over target after it (true Rp)."""
    import math

    from steadytouch import skin

    rng = np.random.default_rng(k_seed)
    for _ in range(k + 1):
        mk = bench.random_electrode(rng)
    e = mk()
    c = sc.Controller(*bench.LIMITS)
    c.calibrate(1000, 1000, round(e.rp_kohm(1000, 1000) * 1000), bench.X, bench.Y)
    c.set_mode(sc.MODE_FAST)
    c.set_skin(*skin.fit([(i, t, round(bench._rp_on(e, i, t))) for i, t in skin.sweep(1000, 1000)]).args())
    ev = {x.pulse: x for x in (events or bench.STUDY_EVENTS)}
    worst = -1.0
    for p in range(n):
        if p in ev:
            e.contact = ev[p].contact if ev[p].contact is not None else e.contact
            e.h = ev[p].h if ev[p].h is not None else e.h
        i, t = c.i_ua, c.t_us
        rp = e.rp_kohm(i, t) * 1000
        assert math.isfinite(rp) and i > 0
        if p > bad_pulse:
            mq = (i * t - bench.Y) * 1000 / (round(rp) - bench.X)
            worst = max(worst, (mq - c.mq_target_fc_per_ohm) / c.mq_target_fc_per_ohm)
        c.update(round(rp * (factor if p == bad_pulse else 1.0)))
    return worst


@pytest.mark.parametrize("case", [(13, 34, 251, 0.8), (19, 17, 251, 0.8), (7, 10, 251, 0.8), (19, 19, 252, 1.5)])
def test_a_bad_read_right_after_a_peel_does_not_ride_a_refit_into_the_ceiling(case):
    """Review of session 18 (HIGH): one Rp read 20 % low (or 50 % high) one or two pulses after a
    half peel, the core alone. The peel's pulse had no model answer (marked); the next jump refitted
    Cp on the pair, the bad read took Cp 1.7 octave down, the next reading missed that model by more
    than Rp/8, and its refit (on the bad read and a good one) put Cp back near the fitted one; that
    jump was not fresh, so rule 6 did not halve its rise into the duration ceiling: +163 % felt
    (seed 13, electrode 34; +0.1 % before the step mark). Rule 6 now also halves a rise into the
    ceiling after a miss above Rp/8 of a model whose Cp a refit had set, refit or not. (The
    firmware's supervisor holds any raise for a confirming reading besides.)"""
    assert exact_run_with_a_bad_read(*case) <= 0.10


def test_a_second_step_one_pulse_after_a_peel_does_not_ride_the_marked_refit():
    """Review of session 18 (MEDIUM): half peeled, then 25 % contact one pulse later (seed 13,
    electrode 4, core alone). Our own large step hid the second step from the step test, so the
    marked pair's refit straddled it (Cp 14.3 for a true 13.0); the next pulse hardly moved I, so
    nothing checked that Cp, and the jump rose into the ceiling at a higher current: +32.5 % felt.
    While a refitted Cp is unchecked, such a rise is now held to fast_step's bound there (the
    Newton step with Rp falling at most as 1/I, at least I_k at t_max), and rule 6 does not halve
    it again (below I_k Rp rises: a first version did, and the +20 kOhm step at 700 uA with 0.3 %
    noise read past RP_MAX and stopped): -21.6 %, then +2.2 %."""
    events = [bench.Event(60, contact=0.5), bench.Event(61, contact=0.25)]
    assert exact_run_with_a_bad_read(13, 4, 58, 1.0, n=90, events=events) <= 0.05
