"""The electrode model MODE_FAST may use (Controller.set_skin), fitted to pulses
measured on one person at one site: Rp(I, T) = Rs + R(I) (1 - exp(-T / (R(I) Cp))),
R(I) = S (I / 1 mA)**-beta (docs/simulation.md; docs/controller.md, "The skin model").

The pulses are the calibration's own: Exp. 1's matched points (the paper used 11,
T = 200...700 us) or `sweep()` along the mE curve through the operating point.
Units: current uA, duration us, resistance ohm, capacitance pF.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

import decay
import sensation_core as sc

SWEEP_T_US = tuple(range(200, 701, 50))  # the paper's Exp. 1 durations


class SkinFitError(ValueError):
    """Pulses that cannot determine the model; the message says why."""


@dataclass
class SkinModel:
    rs_ohm: int
    beta_q16: int
    cp_pf: int
    s_ohm: float  # R at 1 mA on the fitted skin (for reference: the device re-anchors it)
    worst_misfit: float  # largest |model - measured| / measured over the pulses

    @property
    def beta(self) -> float:
        return self.beta_q16 / 65536

    def args(self) -> tuple[int, int, int]:
        """(rs_ohm, beta_q16, cp_pf) for Controller.set_skin / the device command."""
        return self.rs_ohm, self.beta_q16, self.cp_pf


def rp_ohm(i_ua, t_us, rs_ohm, beta, s_ohm, cp_pf):
    """The model's Rp (float, ohm); numpy arrays welcome."""
    r = s_ohm * (np.asarray(i_ua, float) / 1000.0) ** (-beta)
    return rs_ohm + r * (1.0 - np.exp(-np.asarray(t_us, float) * 1e6 / (r * cp_pf)))


def sweep(i0_ua: int, t0_us: int) -> list[tuple[int, int]]:
    """Pulses of the same mE as (i0, t0) at the Exp. 1 durations, and (i0, t0) itself."""
    me = i0_ua * i0_ua * t0_us
    return [(i0_ua, t0_us)] + [(round(math.sqrt(me / t)), t) for t in SWEEP_T_US if t != t0_us]


def load(path) -> list[tuple[float, float, float]]:
    """(i_ua, t_us, rp_ohm) rows of a CSV with those columns (a header row; other
    columns, e.g. Exp. 1's participant and condition, are ignored)."""
    from .files import csv_rows, read_text_file
    from .fit import _num  # the same row checks and messages as `steadytouch fit`

    table = csv_rows(path, read_text_file(path, "CSV file"))
    need = ("i_ua", "t_us", "rp_ohm")
    head = [h.strip() for h in table[0]] if table else []
    if not set(need) <= set(head):
        raise SkinFitError(f"{path}: needs the columns i_ua, t_us, rp_ohm (header: {', '.join(head) or 'none'})")
    ix = [head.index(k) for k in need]
    rows = []
    for n, row in enumerate(table[1:], start=2):
        if not any(c.strip() for c in row):
            continue
        rows.append(tuple(_num(path, n, k, row[j] if j < len(row) else None) for k, j in zip(need, ix)))
    return rows


def fit(pulses) -> SkinModel:
    """Least-squares fit (relative residuals) of Rs, beta, S, Cp to (i_ua, t_us, rp_ohm)
    rows. Needs at least 5 pulses with at least 3 different durations."""
    a = np.asarray(list(pulses), float)
    if a.ndim != 2 or a.shape[1] != 3 or len(a) < 5:
        raise SkinFitError(f"need at least 5 pulses (i_ua, t_us, rp_ohm), got {len(a)}")
    if len(set(a[:, 1])) < 3:
        raise SkinFitError("need pulses of at least 3 different durations")
    if (a <= 0).any():
        raise SkinFitError("every current, duration and Rp must be > 0")
    i, t, r = a.T

    def res(p):
        return rp_ohm(i, t, p[0], p[1], math.exp(p[2]), math.exp(p[3])) / r - 1.0

    lo = [0.0, sc.SKIN_BETA_MIN_Q16 / 65536, math.log(100.0), math.log(sc.SKIN_CP_MIN_PF)]
    hi = [sc.SKIN_RS_MAX_OHM, sc.SKIN_BETA_MAX_Q16 / 65536, math.log(1e7), math.log(sc.SKIN_CP_MAX_PF)]
    best = None
    for beta0 in (0.5, 0.75):
        for cp0 in (3000.0, 15000.0, 60000.0):
            x0 = np.clip([min(500.0, 0.5 * r.min()), beta0, math.log(float(np.median(r))), math.log(cp0)],
                         np.add(lo, 1e-9), np.subtract(hi, 1e-9))  # inside the bounds whatever the data
            f = least_squares(res, x0, bounds=(lo, hi), x_scale=[500.0, 0.1, 0.5, 0.5])
            if best is None or f.cost < best.cost:
                best = f
    rs, beta, ls, lc = best.x
    if not np.all(np.isfinite(best.x)) or not np.isfinite(best.cost):
        raise SkinFitError("the fit did not converge: the pulses do not determine the model")
    m = SkinModel(round(rs), round(beta * 65536), round(math.exp(lc)), math.exp(ls), 0.0)
    m.worst_misfit = float(np.max(np.abs(rp_ohm(i, t, m.rs_ohm, m.beta, m.s_ohm, m.cp_pf) / r - 1.0)))
    return m


# ---- repeated sweeps: an averaged fit that knows its own uncertainty ----
TRUST_SHAPE_SD = 0.01  # the model is sent only if its predicted Rp shape is known to 1 % (1 sd) ...
TRUST_MISFIT = 0.02  # ... and it fits the averaged pulses within 2 %
RECOMMENDED_SWEEPS = 30  # sweep_wide 30 times: 330 pulses, 6.6 s at 50 Hz (docs/calibration.md)


@dataclass
class SweepFit:
    """A model fitted to the mean of repeated calibration sweeps, and how well it is known.

    shape_sd: the largest standard error, over the operating region, of the model's
    Rp(I, T) / Rp(I0, T0) (what MODE_FAST extrapolates with: the device re-anchors
    the scale), from the fits to each sweep alone (sd of the mean: spread / sqrt(n)).
    trusted: whether to send it; otherwise MODE_FAST runs model-free (the host decides)."""

    model: SkinModel | None
    sweeps: int
    shape_sd: float
    misfit: float
    trusted: bool
    why: str

    def args(self) -> tuple[int, int, int]:
        """What to send with set_skin: the model, or (0, 0, 0) = none (model-free step)."""
        return self.model.args() if self.trusted else (0, 0, 0)


def _shape(m: SkinModel, i0_ua, t0_us, grid):
    i, t = grid
    return rp_ohm(i, t, m.rs_ohm, m.beta, m.s_ohm, m.cp_pf) / float(rp_ohm(i0_ua, t0_us, m.rs_ohm, m.beta, m.s_ohm,
                                                                           m.cp_pf))


def operating_grid(i0_ua: int, t0_us: int, t_max_us: int = 8000):
    """(I, T) where MODE_FAST uses the model: along and around the calibration's mE
    curve, T from 50 us to t_max, I from I0/4 to 4 I0."""
    me = i0_ua * i0_ua * t0_us
    ts = np.geomspace(50, t_max_us, 12)
    pts = [(math.sqrt(me / t) * f, t) for t in ts for f in (0.5, 1.0, 2.0)]
    pts = [(i, t) for i, t in pts if i0_ua / 4 <= i <= 4 * i0_ua]
    return np.array([p[0] for p in pts]), np.array([p[1] for p in pts])


SWEEPS_MOST = 60  # sweeps_for_trust asks for at most this many in all (660 pulses, 13.2 s at 50 Hz)


def sweeps_for_trust(f: SweepFit, most: int = SWEEPS_MOST) -> int | None:
    """How many sweeps in all should bring an untrusted fit's shape within TRUST_SHAPE_SD: its
    standard error falls as 1/sqrt(n), so n x (sd / limit)**2, with a tenth more for the sd's own
    scatter and at least 5 more than were given (fewer than 3 sweeps: RECOMMENDED_SWEEPS). None
    when the fit is trusted, when it is refused for its misfit (more of the same pulses do not
    change the model's form), or when more than `most` would be needed (an electrode read too
    noisily for a model: MODE_FAST stays model-free)."""
    if f.trusted or f.shape_sd <= TRUST_SHAPE_SD:
        return None
    if not math.isfinite(f.shape_sd):  # fewer than 3 sweeps: no spread to project from
        return max(RECOMMENDED_SWEEPS, f.sweeps + 5)
    n = max(f.sweeps + 5, math.ceil(f.sweeps * (f.shape_sd / TRUST_SHAPE_SD) ** 2 * 1.1))
    return n if n <= most else None


def fit_sweeps(sweeps, i0_ua: int, t0_us: int, t_max_us: int = 8000) -> SweepFit:
    """sweeps: a list of repeated sweeps, each a list of (i_ua, t_us, rp_ohm) over the
    same pulses. Fits the per-pulse mean; the uncertainty comes from fitting each sweep."""
    if not sweeps:
        raise SkinFitError("no sweeps")
    pulses = [(i, t) for i, t, _ in sweeps[0]]
    if any([(i, t) for i, t, _ in s] != pulses for s in sweeps):
        raise SkinFitError("every sweep must have the same pulses in the same order")
    mean = [(i, t, float(np.mean([s[k][2] for s in sweeps]))) for k, (i, t) in enumerate(pulses)]
    m = fit(mean)
    grid = operating_grid(i0_ua, t0_us, t_max_us)
    if len(sweeps) >= 3:
        shapes = np.array([_shape(fit(s), i0_ua, t0_us, grid) for s in sweeps])
        sd = float(np.max(np.std(shapes, axis=0, ddof=1) / np.sqrt(len(sweeps)) / np.mean(shapes, axis=0)))
    else:
        sd = float("inf")  # cannot tell: not sent
    why = ""
    if sd > TRUST_SHAPE_SD:
        why = f"its Rp shape is known only to {sd:.2%} (limit {TRUST_SHAPE_SD:.0%}, {len(sweeps)} sweeps)"
    elif m.worst_misfit > TRUST_MISFIT:
        why = f"it misses the averaged pulses by up to {m.worst_misfit:.2%} (limit {TRUST_MISFIT:.0%})"
    return SweepFit(m, len(sweeps), sd, m.worst_misfit, not why, why)


# ---- rule 7: the monitor's tau gain, measured on the same sweeps ----
# After each pulse the monitor's decay gives tau = R(I) Cp (telemetry's ltau_q16: log2 tau in us, Q.16; 0 none).
# MODE_FAST's jump may anchor S and Cp on it (docs/controller.md, rule 7) only if the monitor reads it true: a filter
# or a lead that scales the decay makes the jumps overshoot (x 2: +40 % felt). The sweeps the model is fitted to are
# on the same skin at the same time, so the fitted model's tau on each sweep pulse is what a true monitor reads: the
# median log2 (tau read / the model's) is the monitor's gain (sent with the model, taken out of every tau), the
# slope of log tau read on log tau model tells a scale (1) from an offset (a lead's +50 us: below 1), and their
# spread how well the decay is read. Past any bound, tau is not used (the model still is).
TAU_MIN_READS = 20  # taus read on the sweeps (and at least half of their pulses)
TAU_SPREAD_MAX = 0.15  # octave: the interquartile range of the log2 ratios
TAU_SLOPE = (0.97, 1.04)  # log tau read on log tau model: a scale keeps 1, an additive error flattens it
TAU_SPAN_MIN = 0.5  # octave of the model's tau the sweeps must span to tell a slope


@dataclass
class TauGain:
    """The monitor's tau gain measured on the calibration sweeps (tau_gain): q16 is what set_skin takes
    (log2 gain, Q.16), sc.SKIN_TAU_OFF when tau is not to be used (why says why)."""

    q16: int
    reads: int
    gain_oct: float
    spread_oct: float
    slope: float
    trusted: bool
    why: str


def tau_gain(m: SkinModel, taus) -> TauGain:
    """taus: (i_ua, t_us, ltau_q16) of every sweep pulse (ltau_q16 0: no tau read); m: the model fitted to
    those sweeps."""
    a = np.asarray([(i, t, lt) for i, t, lt in taus], float).reshape(-1, 3)
    ok = a[:, 2] > 0
    n = int(ok.sum())
    if n < TAU_MIN_READS or 2 * n < len(a):
        return TauGain(sc.SKIN_TAU_OFF, n, math.nan, math.nan, math.nan, False,
                       f"tau was read on {n} of {len(a)} sweep pulses (need {TAU_MIN_READS} and half)")
    i, lt = a[ok, 0], a[ok, 2] / 65536.0
    lm = np.log2(m.s_ohm * (i / 1000.0) ** (-m.beta) * m.cp_pf / 1e6)  # the model's tau (us), log2
    d = lt - lm
    g = float(np.median(d))
    q1, q3 = np.percentile(d, [25, 75])
    spread = float(q3 - q1)
    span = float(lm.max() - lm.min())
    slope = float(np.polyfit(lm, lt, 1)[0]) if span > 0 else math.nan
    q16 = round(g * 65536)
    why = ""
    if abs(q16) > sc.SKIN_TAU_MAX_Q16:
        why = f"the monitor reads tau x {2 ** g:.2f} (limit x {2 ** (-sc.SKIN_TAU_MAX_Q16 / 65536):.2f}..x " \
              f"{2 ** (sc.SKIN_TAU_MAX_Q16 / 65536):.2f}): check its filter and leads"
    elif spread > TAU_SPREAD_MAX:
        why = f"tau's reads spread over {spread:.2f} octave (limit {TAU_SPREAD_MAX})"
    elif span < TAU_SPAN_MIN:
        why = f"the sweeps span {span:.2f} octave of tau (need {TAU_SPAN_MIN}: sweep_wide's durations)"
    elif not TAU_SLOPE[0] <= slope <= TAU_SLOPE[1]:
        why = f"tau read follows the model's with slope {slope:.3f} (accepted {TAU_SLOPE[0]}..{TAU_SLOPE[1]}: " \
              "an offset in the decay, not a gain)"
    return TauGain(sc.SKIN_TAU_OFF if why else q16, n, g, spread, slope, not why, why)


WIDE_T_US = (100, 150, 200, 300, 400, 500, 700, 1000, 1500, 2000, 3000)


def sweep_wide(i0_ua: int, t0_us: int, t_max_us: int = 8000) -> list[tuple[int, int]]:
    """Like sweep(), same mE, over 100-3000 us: the wider the durations, the better beta,
    Cp and Rs are told apart (MODE_FAST extrapolates to where a step takes the pulse)."""
    me = i0_ua * i0_ua * t0_us
    return [(i0_ua, t0_us)] + [(round(math.sqrt(me / t)), t) for t in WIDE_T_US if t != t0_us and t <= t_max_us]


def _column(path, name) -> list[tuple[int, str]] | None:
    """(line, cell) of column `name` on each data row load() reads (blank rows skipped), None without it."""
    from .files import csv_rows, read_text_file

    table = csv_rows(path, read_text_file(path, "CSV file"))
    head = [h.strip() for h in table[0]]
    if name not in head:
        return None
    j = head.index(name)
    return [(n, r[j].strip() if j < len(r) else "") for n, r in enumerate(table[1:], start=2) if any(c.strip() for c in r)]


def load_taus(path) -> list[tuple[float, float, int]] | None:
    """(i_ua, t_us, ltau_q16) of every row of a sweeps CSV with an `ltau_q16` column (as `record` writes it:
    the decay's log2 tau after each pulse, Q.16; 0: none read), for tau_gain; None without that column."""
    rows = load(path)
    cells = _column(path, "ltau_q16")
    if cells is None:
        return None
    out = []
    for (n, v), (i, t, _) in zip(cells, rows):
        try:
            lt = int(v)
        except ValueError:
            raise SkinFitError(f"{path} row {n}: column ltau_q16 is not a whole number: {v!r}") from None
        if not 0 <= lt < decay.LTAU_END:
            raise SkinFitError(f"{path} row {n}: column ltau_q16 = {lt} out of range 0..{decay.LTAU_END - 1} "
                               "(log2 tau in us, Q.16; 0: none)")
        out.append((i, t, lt))
    return out


def whole_sweeps(sweeps) -> tuple[list, list[int]]:
    """The sweeps without those cut short (an interrupted `steadytouch sweep`: the first pulses of a whole
    sweep, fewer of them), and the indices of those left out."""
    if len(sweeps) < 2:
        return sweeps, []
    full = [p[:2] for p in max(sweeps, key=len)]
    cut = [k for k, w in enumerate(sweeps) if len(w) < len(full) and [p[:2] for p in w] == full[:len(w)]]
    return [w for k, w in enumerate(sweeps) if k not in cut], cut


def load_sweeps(path) -> list[list[tuple[float, float, float]]]:
    """Repeated sweeps from a CSV with i_ua, t_us, rp_ohm and a `sweep` column (rows of
    one sweep share its value; every sweep the same pulses in the same order). Without
    a `sweep` column: one sweep."""
    rows = load(path)
    cells = _column(path, "sweep")
    if cells is None:
        return [rows]
    groups: dict[str, list] = {}
    for (_, sid), row in zip(cells, rows):
        groups.setdefault(sid, []).append(row)
    return list(groups.values())
