"""Every controller mode x every simulated disturbance, on the simulated electrode.

Run: .venv/bin/python bench/controllers.py [--noise 0] [--plots docs/img]

The integer core (shared/sensation_core.py, CPython) drives the electrode model
(firmware/sim_electrode.py) pulse by pulse; Rp is read as the model's
end-of-pulse value rounded to 1 ohm (plus Gaussian noise if --noise, relative).
Metrics per run (docs/performance.md explains them):
- settle: pulses after a disturbance until |mQ - target| stays below the
  threshold (25 fC/ohm = 2.5e-5 uC/kohm, or the resolution of the pulse there:
  the mQ change of 0.5 us and 0.5 uA, if larger); pulse 0 is the first pulse
  measured on the changed skin, so 1 is the physical limit; "-" never settles;
- mQ / mE RMS and peak relative error over the run (pulses with a pulse);
- overshoot (shock risk): the largest current and charge above the range
  between their values before the disturbance and after settling, in % of
  that end value; "dip": the current's largest excursion below that range;
- floor: pulses held at a sensation floor (I at i_min or T at t_min).
Besides the six core modes the table has an "oracle" row: not a controller a
device could run, but the law solved each pulse on the true simulated skin as
it was at the pulse just measured, through the core's bounds, then the integer
pulse nearest the line on that skin. After a step it is what full knowledge
of the skin gives (pulse 0, measured before anyone knew, is lost to every
controller); under a drift it still lags one pulse, so a controller that
predicts the drift can beat it there. Where the oracle itself misses a target
after a step, the target is out of reach in this electrode (the summary at
the end says which).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT / "shared"), str(ROOT / "firmware"), str(ROOT)]
import sensation_core as sc  # noqa: E402
from host import skin  # noqa: E402
from sim_electrode import Electrode  # noqa: E402

X, Y = -1670, 186000
LIMITS = (100, 10000, 50, 8000, 10_000_000)
MODE_NAMES = {sc.MODE_OPEN_LOOP: "open", sc.MODE_CONSTANT_CHARGE: "charge", sc.MODE_CONSTANT_ENERGY: "energy",
              sc.MODE_PULSE_WIDTH_LINEAR: "pwlinear", sc.MODE_AKHTAR: "akhtar", sc.MODE_FAST: "fast"}
ORACLE = -1  # not a core mode: the bench's reference for what is physically possible
FAST_NO_MODEL = -2  # MODE_FAST without a skin model (set_skin not called)
ALL_NAMES = {**MODE_NAMES, FAST_NO_MODEL: "fast, no model", ORACLE: "oracle"}


def _rp_on(e, i_ua, t_us):
    """Rp (ohm) a pulse would read on e's skin as it is now, without touching e."""
    probe = Electrode(e.area0, e.rs, e.rho_ref, e.j_ref, e.beta, e.c, 1.0)
    probe.contact, probe.h = e.contact, e.h
    return probe.rp_kohm(i_ua, t_us) * 1000


def mq_of(c):
    """The calibrated mQ of controller c in pC/ohm (float)."""
    return (c.i0_ua * c.t0_us - c.y_star_pc) / (c.rp0_ohm - c.x_star_ohm)


def best_pulse(c, e, i_ua, t_us, ceiling=False):
    """The integer pulse around (i_ua, t_us), within the limits, that lands nearest
    the calibrated Q-Rp line on e's skin as it is now (at the ceiling: I around
    i_ua, each with the duration <= t_max that puts it on the line)."""
    mq = mq_of(c)
    best = None
    pairs = [(i, t) for t in (t_us - 1, t_us, t_us + 1) for i in (i_ua - 1, i_ua, i_ua + 1)]
    if ceiling:
        pairs = []
        for i in range(i_ua - 2, i_ua + 3):
            if i > 0:
                t = min(c.t_max_us, round((Y + mq * (_rp_on(e, i, c.t_max_us) - X)) / i))
                pairs += [(i, t - 1), (i, t), (i, t + 1)]
    for i, t in pairs:
        if not (c.i_min_ua <= i <= c.i_max_ua and c.t_min_us <= t <= c.t_max_us and i * t <= c.q_max_pc):
            continue
        err = abs(i * t - Y - mq * (_rp_on(e, i, t) - X))
        if best is None or err < best[0]:
            best = (err, i, t)
    return (best[1], best[2]) if best else (i_ua, t_us)


def nearest_root(f, u0, step=0.05, n=80):
    """The root of f nearest u0: widen by `step` on both sides until f changes sign
    within one step (steps where f is not finite are passed over), then bisect.
    None if there is no sign change within n steps."""
    for k in range(1, n + 1):
        for lo, hi in ((u0 - step * k, u0 - step * (k - 1)), (u0 + step * (k - 1), u0 + step * k)):
            a, b = f(lo), f(hi)
            if not (math.isfinite(a) and math.isfinite(b)) or (a > 0) == (b > 0):
                continue
            for _ in range(50):
                m = 0.5 * (lo + hi)
                if (f(m) > 0) == (a > 0):
                    lo = m
                else:
                    hi = m
            return 0.5 * (lo + hi)
    return None


def oracle_current_at(c, e, t_us, i_ua):
    """The current that puts a pulse of duration t_us on the Q-Rp line on e's skin
    as it is now (the root nearest i_ua; i_ua itself if there is none)."""
    mq = mq_of(c)
    u = nearest_root(lambda u: Y + mq * (_rp_on(e, math.exp(u), t_us) - X) - math.exp(u) * t_us, math.log(i_ua))
    return i_ua if u is None else math.exp(u)


def oracle_charge(c, e, q_pc):
    """The law's self-consistent charge on e's skin as it is now: the root of
    Q = y* + mQ (Rp(mE/Q, Q^2/mE) - x*) nearest q_pc along the mE curve (pC)."""
    me = c.i0_ua * c.i0_ua * c.t0_us
    mq = mq_of(c)

    def f(lq):
        q = math.exp(lq)
        return Y + mq * (_rp_on(e, me / q, q * q / me) - X) - q

    u = nearest_root(f, math.log(q_pc))
    return c.q_max_pc * 2.0 if u is None else math.exp(u)  # none within e^4: beyond every bound


def oracle_pulse(c, e, q_pc):
    """Replace c's proposal (the paper's step, just made) by the law solved on the true
    skin e, through the core's bounds, then the integer pulse nearest the line there."""
    paper = (c.i_ua, c.t_us, c.status)
    q = oracle_charge(c, e, q_pc)
    c._from_q(min(int(q * 16), 2**29))
    if c.status & sc.ST_T_MAX:  # the ceiling keeps the line: solve for I at t_max
        i_line = oracle_current_at(c, e, c.t_max_us, c.i_ua)
        if (c.i_min_ua <= i_line <= c.i_max_ua and i_line * c.t_max_us <= c.q_max_pc
                and _rp_on(e, i_line, c.t_max_us) <= sc.RP_MAX_OHM):
            c.i_ua, c.t_us = best_pulse(c, e, round(i_line), c.t_max_us, ceiling=True)
        else:  # no pulse within the limits is on the line: the paper's step
            c.i_ua, c.t_us, c.status = paper
    elif c.status == sc.ST_OK:
        c.i_ua, c.t_us = best_pulse(c, e, round(q / c.t_us), c.t_us)


@dataclass
class Event:
    pulse: int  # the first pulse measured on the changed skin
    contact: float | None = None
    h: float | None = None
    h_tau_pulses: float = 0.0  # hydration relaxes with this time constant (pulses); 0 = a step


def scenario_events(name):
    if name == "gel":
        return [Event(50, h=0.3, h_tau_pulses=50), Event(800, h=0.7, h_tau_pulses=100)], 1600
    if name == "gel-step":
        return [Event(50, h=0.3), Event(250, h=0.7)], 450
    if name.startswith("peel"):
        return [Event(50, contact=0.75), Event(300, contact=0.5), Event(550, contact=0.25), Event(800, contact=1.0)], 1050
    if name == "exercise":  # 5 min stairs (h -> 0.4, tau 2 min), 10 min rest (tau 8 min), at 50 Hz
        return [Event(100, h=0.4, h_tau_pulses=6000), Event(15100, h=1.0, h_tau_pulses=24000)], 45100
    if name == "off":
        return [Event(50, contact=0.0)], 100
    raise ValueError(name)


def run(mode, events, n, i0=1000, t0=1000, noise=0.0, seed=1, h_start=1.0):
    rng = np.random.default_rng(seed)
    e = Electrode()
    e.h = h_start
    c = sc.Controller(*LIMITS)
    rp0 = round(e.rp_kohm(i0, t0) * 1000)
    c.calibrate(i0, t0, rp0, X, Y)
    c.set_mode(mode if mode >= 0 else sc.MODE_FAST if mode == FAST_NO_MODEL else sc.MODE_AKHTAR)
    if mode == sc.MODE_FAST:  # the skin model, fitted to the calibration's pulses (Exp. 1's durations)
        pulses = [(i, t, round(_rp_on(e, i, t) * (1 + noise * rng.normal()))) for i, t in skin.sweep(i0, t0)]
        c.set_skin(*skin.fit(pulses).args())
    h_target, tau = e.h, 0.0
    rows = []
    ev = {x.pulse: x for x in events}
    for k in range(n):
        if k in ev:
            x = ev[k]
            if x.contact is not None:
                e.contact = x.contact
            if x.h is not None:
                h_target, tau = x.h, x.h_tau_pulses
                if tau == 0:
                    e.h = h_target
        if tau > 0:
            e.h += (h_target - e.h) * (1 - math.exp(-1 / tau))
        i, t = c.i_ua, c.t_us
        if i == 0:
            rows.append((k, 0, 0, 0, float("nan"), c.status))
            continue
        rp_k = e.rp_kohm(i, t) * 1000
        if not math.isfinite(rp_k) or rp_k > 1e9:
            rp = sc.RP_OVER
        else:
            rp = round(rp_k * (1 + noise * rng.normal()))
        mq = (i * t - Y) * 1000 / (rp - X) if rp < sc.RP_OVER else float("nan")
        rows.append((k, i, t, rp, mq, c.status))
        c.update(rp)
        if mode == ORACLE and c.i_ua > 0:
            oracle_pulse(c, e, i * t)
    return np.array(rows, dtype=float), c.mq_target_fc_per_ohm, c.me_ua2ms * 1000


def metrics(rows, target, me, events, n):
    k, i, t, rp, mq, st = rows.T
    on = i > 0
    err = np.where(on, mq - target, np.nan)
    thr = np.maximum(25.0, (0.5 * i + 0.5 * t) * 1000 / np.maximum(rp - X, 1))
    starts = [x.pulse for x in events] + [n]
    settles, over_i, over_q, under_i = [], [], [], []
    for a, b in zip(starts, starts[1:]):
        seg = slice(a, b)
        ok = np.abs(err[seg]) < thr[seg]
        ok &= on[seg]
        s = None
        for j in range(len(ok)):
            if ok[j:].all():
                s = j
                break
        settles.append(s)
        if s is not None and a > 0:
            before_i, after_i = i[a - 1], i[a + s]
            before_q, after_q = i[a - 1] * t[a - 1], i[a + s] * t[a + s]
            lo_i, hi_i = min(before_i, after_i), max(before_i, after_i)
            hi_q = max(before_q, after_q)
            ii, qq = i[a : a + s + 1], i[a : a + s + 1] * t[a : a + s + 1]
            # overshoot (shock risk): current or charge above the range; a dip of the
            # current below it (less sensation, not a shock) is reported on its own
            over_i.append(max(0.0, (ii.max() - hi_i) / hi_i))
            over_q.append(max(0.0, (qq.max() - hi_q) / hi_q))
            under_i.append(max(0.0, (lo_i - ii[ii > 0].min()) / lo_i) if (ii > 0).any() else 0.0)
    rel_q = err[on] / target
    rel_e = (i[on] ** 2 * t[on] - me) / me
    floor = int(np.sum(((st.astype(int) & (sc.ST_I_MIN | sc.ST_T_MIN)) > 0) & on))
    return {
        "settle": settles, "rms_q": float(np.sqrt(np.nanmean(rel_q**2))), "peak_q": float(np.nanmax(np.abs(rel_q))),
        "rms_e": float(np.sqrt(np.mean(rel_e**2))), "peak_e": float(np.max(np.abs(rel_e))),
        "over_i": max(over_i, default=0.0), "over_q": max(over_q, default=0.0),
        "under_i": max(under_i, default=0.0), "floor": floor,
    }


def step_events(i0, delta_kohm):
    """A step of delta in Rp at the operating point (fixed I, T), made by scaling hydration."""
    e = Electrode()
    r0 = e.rp_kohm(i0, 1000)
    target = r0 + delta_kohm
    lo, hi = 0.01, 20.0
    for _ in range(60):
        h = math.sqrt(lo * hi)
        e2 = Electrode()
        e2.h = h
        if e2.rp_kohm(i0, 1000) < target:
            lo = h
        else:
            hi = h
    return [Event(50, h=h), Event(300, h=1.0)], 550


def fmt_settle(v):
    return "-" if v is None else str(v)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise", type=float, default=0.0, help="relative Rp measurement noise (default 0)")
    ap.add_argument("--plots", default="", help="folder for one PNG per scenario (default: none)")
    a = ap.parse_args()
    cases = []
    for name in ("gel-step", "gel", "peel", "exercise", "off"):
        ev, n = scenario_events(name)
        cases.append((name, 1000, ev, n))
    for i0 in (700, 1000, 2000):
        for d in (-30, -20, -10, 10, 20, 50):
            r0 = Electrode().rp_kohm(i0, 1000)
            if r0 + d < 3:
                continue
            ev, n = step_events(i0, d)
            cases.append((f"step {d:+d} kohm @ {i0} uA ({r0:.0f} kohm)", i0, ev, n))
    print("| scenario | mode | pulses to settle (each disturbance) | mQ RMS / peak | mE RMS / peak | overshoot I / Q | dip I | pulses at a floor |")
    print("|---|---|---|---|---|---|---|---|")
    summary = {}
    for name, i0, ev, n in cases:
        runs = {}
        for mode in ALL_NAMES:
            rows, target, me = run(mode, ev, n, i0=i0, noise=a.noise)
            m = metrics(rows, target, me, ev, n)
            runs[mode] = (rows, target)
            summary[(name, mode)] = m
            print(f"| {name} | {ALL_NAMES[mode]} | {', '.join(fmt_settle(s) for s in m['settle'])} | "
                  f"{m['rms_q']:.2%} / {m['peak_q']:.1%} | {m['rms_e']:.2%} / {m['peak_e']:.1%} | "
                  f"{m['over_i']:.1%} / {m['over_q']:.1%} | {m['under_i']:.1%} | {m['floor']} |")
        if a.plots and not name.startswith("step") or (a.plots and name.startswith("step -30 kohm @ 1000")):
            plot(name, runs, Path(a.plots))
    # the criteria for MODE_FAST against the paper's mode; the oracle
    # (the law solved on the true skin each pulse) shows where a target is out of
    # reach of any controller that measures one Rp per pulse
    print()
    fails, impossible, drifts = [], [], []
    for name, _, ev, _ in cases:
        ak, fa, orc = (summary[(name, m)] for m in (sc.MODE_AKHTAR, sc.MODE_FAST, ORACLE))
        for j, (sa, sf, so) in enumerate(zip(ak["settle"], fa["settle"], orc["settle"])):
            if ev[j].h_tau_pulses > 0:  # a drift, not a step: the 2-pulse target is about steps
                drifts.append(f"{name} #{j}: fast {fmt_settle(sf)} (akhtar {fmt_settle(sa)}, oracle {fmt_settle(so)})")
                continue
            if (sa is None or sa > 2) and (sf is None or sf > 2):
                line = f"{name} #{j}: fast {fmt_settle(sf)} (akhtar {fmt_settle(sa)}, oracle {fmt_settle(so)})"
                (impossible if so is None or so > 2 else fails).append(line)
        if fa["rms_q"] > ak["rms_q"] / 2 + 1e-4:  # (+1e-4: a run with no error to speak of)
            line = (f"{name}: fast mQ RMS {fa['rms_q']:.2%} > half of akhtar's {ak['rms_q']:.2%} "
                    f"(oracle {orc['rms_q']:.2%})")
            (impossible if orc["rms_q"] > ak["rms_q"] / 2 + 1e-4 else fails).append(line)
        if fa["over_i"] > 0.05 or fa["over_q"] > 0.05:
            fails.append(f"{name}: fast overshoot I {fa['over_i']:.1%} / Q {fa['over_q']:.1%}")
    print(f"MODE_FAST criteria: {len(fails)} not met, {len(impossible)} out of reach of the oracle too "
          f"({len(drifts)} drift disturbances listed apart)")
    for f in fails:
        print("  - not met: " + f)
    for f in impossible:
        print("  - out of reach: " + f)
    for f in drifts:
        print("  - drift (the skin keeps moving; settling is not a step's): " + f)


def plot(name, runs, out: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for mode, (rows, target) in runs.items():
        k, i, t, rp, mq, st = rows.T
        lw = 1.6 if mode in (sc.MODE_AKHTAR, sc.MODE_FAST) else 0.8
        ls = ":" if mode == ORACLE else "-"
        ax[0].plot(k, rp / 1e3, lw=lw, ls=ls, label=ALL_NAMES[mode])
        ax[1].plot(k, i / 1e3, lw=lw, ls=ls)
        ax[2].plot(k, (mq - target) / 1e6, lw=lw, ls=ls)
    ax[0].set_ylabel("Rp (kΩ)")
    ax[1].set_ylabel("I (mA)")
    ax[2].set_ylabel("mQ − target (µC/kΩ)")
    ax[2].set_ylim(-0.01, 0.01)
    ax[2].set_xlabel("pulse")
    ax[0].legend(fontsize=7, ncol=3)
    ax[0].set_title(name)
    for x in ax:
        x.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / ("controllers-" + name.split(" ")[0] + ".png"), dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    main()
