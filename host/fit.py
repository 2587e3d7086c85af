"""The paper's modelling experiment (Exp. 1, Fig. 2, note S4) as a tool: lines of
constant sensation in the Ep-Rp and Q-Rp planes and their common convergence
point (x*, y*); and Exp. 2's check of the controller's predictions (Fig. 4E).

Input schema (docs/calibration.md): CSV with a header and the columns
participant, condition, t_us, i_ua and one of vp_mv / rp_ohm (Exp. 2 adds
trial and initial). Units: Rp in ohm, Q in pC (= uA*us), Ep in erg.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

R2_THRESHOLD = 0.7
# what a data file may hold (beyond: a typo or a unit mistake, and the squares overflow)
RANGES = {"i_ua": (0.0, 100_000.0), "t_us": (0.0, 100_000.0), "rp_ohm": (0.0, 10_000_000.0),
          "vp_mv": (0.0, 1_000_000.0)}
ERG_PER_OHM_UA2_US = 1e-18 * 1e7  # ohm * uA^2 * us = 1e-18 J = 1e-11 erg


class DataError(ValueError):
    """A data file that cannot be used; the message names the file and row."""


@dataclass
class DataSet:
    participant: str
    condition: str
    i_ua: np.ndarray
    t_us: np.ndarray
    rp_ohm: np.ndarray
    trial: str = ""
    initial: int = -1  # Exp. 2: index of the trial's initial point

    @property
    def q_pc(self):
        return self.i_ua * self.t_us

    @property
    def ep_erg(self):
        return self.rp_ohm * self.i_ua**2 * self.t_us * ERG_PER_OHM_UA2_US


def _num(path, line, col, s, positive=True):
    if s is None:
        raise DataError(f"{path} row {line}: column {col} is missing (a short row)")
    try:
        v = float(s)
    except ValueError:
        raise DataError(f"{path} row {line}: column {col} is not a number: {s!r}") from None
    if not np.isfinite(v) or (positive and v <= 0):
        raise DataError(f"{path} row {line}: column {col} must be a positive number, got {s}")
    lo, hi = RANGES.get(col, (-np.inf, np.inf))
    if positive and v > hi:
        raise DataError(f"{path} row {line}: column {col} = {s} out of range (0, {hi:g}]")
    return v


def load(path: Path | str, exp2: bool = False) -> list[DataSet]:
    """Read and check a method-of-adjustment file; DataError names the row on any problem."""
    from .files import csv_rows, read_text_file

    path = Path(path)
    rows = csv_rows(path, read_text_file(path, "CSV file"))
    if not rows:
        raise DataError(f"{path}: empty file")
    head = [h.strip() for h in rows[0]]
    need = ["participant", "condition", "t_us", "i_ua"] + (["trial", "initial"] if exp2 else [])
    missing = [c for c in need if c not in head]
    if "vp_mv" not in head and "rp_ohm" not in head:
        missing.append("vp_mv or rp_ohm")
    if missing:
        raise DataError(f"{path} row 1: missing column(s) {', '.join(missing)}")
    ix = {h: k for k, h in enumerate(head)}
    groups: dict[tuple, list] = {}
    first_line: dict[tuple, int] = {}
    for line, r in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in r):
            continue
        if len(r) != len(head):
            raise DataError(f"{path} row {line}: {len(r)} columns, the header has {len(head)}")
        i = _num(path, line, "i_ua", r[ix["i_ua"]])
        t = _num(path, line, "t_us", r[ix["t_us"]])
        if "rp_ohm" in ix and r[ix["rp_ohm"]].strip():
            rp = _num(path, line, "rp_ohm", r[ix["rp_ohm"]])
        else:
            rp = _num(path, line, "vp_mv", r[ix["vp_mv"]]) * 1000.0 / i
        key = (r[ix["participant"]].strip(), r[ix["condition"]].strip(), r[ix["trial"]].strip() if exp2 else "")
        init = 0
        if exp2:
            init = int(_num(path, line, "initial", r[ix["initial"]], positive=False))
        groups.setdefault(key, []).append((i, t, rp, init))
        first_line.setdefault(key, line)
    if not groups:
        raise DataError(f"{path}: no data rows")
    out = []
    for key, pts in groups.items():
        if len(pts) < 2:
            raise DataError(f"{path} row {first_line[key]}: participant {key[0]}, condition {key[1]} has a single "
                            "point; a line needs at least 2 (the paper used 11)")
        a = np.array(pts)
        who = f"{path} row {first_line[key]}: participant {key[0]}, condition {key[1]}" + (f", trial {key[2]}" if exp2 else "")
        if len(np.unique(a[:, 2])) < 2:
            raise DataError(f"{who}: every point has the same Rp; a line needs at least 2 different Rp")
        if len(np.unique(a[:, 0] * a[:, 1])) < 2:
            raise DataError(f"{who}: every point has the same charge I*T; a line needs at least 2 different Q")
        initial = -1
        if exp2:
            w = np.flatnonzero(a[:, 3] == 1)
            if len(w) != 1:
                raise DataError(f"{path} row {first_line[key]}: trial {key[2]} of {key[0]}/{key[1]} needs exactly one "
                                "row with initial = 1")
            initial = int(w[0])
        out.append(DataSet(key[0], key[1], a[:, 0], a[:, 1], a[:, 2], key[2], initial))
    return out


# ------------------------------------------------------------ statistics
def r2_through_point(x, y, xs: float, ys: float) -> float:
    """Centred r^2 of the least-squares line through (xs, ys)."""
    dx, dy = x - xs, y - ys
    m = (dx @ dy) / (dx @ dx)
    ss_res = np.sum((dy - m * dx) ** 2)
    ss_tot = np.sum((y - y.mean()) ** 2)
    return float(1 - ss_res / ss_tot)


def r2_of_line(x, y, slope: float, xs: float, ys: float) -> float:
    """Centred r^2 of fixed predictions y = ys + slope (x - xs)."""
    ss_res = np.sum((y - (ys + slope * (x - xs))) ** 2)
    return float(1 - ss_res / np.sum((y - y.mean()) ** 2))


class _Moments:
    """Centred moments of every data set, for fast mean-r^2 over many (x*, y*)."""

    def __init__(self, sets: list[DataSet]):
        self.n = np.array([len(s.rp_ohm) for s in sets], float)
        self.rm = np.array([s.rp_ohm.mean() for s in sets])
        self.qm = np.array([s.q_pc.mean() for s in sets])
        self.srr = np.array([np.sum((s.rp_ohm - s.rp_ohm.mean()) ** 2) for s in sets])
        self.sqq = np.array([np.sum((s.q_pc - s.q_pc.mean()) ** 2) for s in sets])
        self.srq = np.array([np.sum((s.rp_ohm - s.rp_ohm.mean()) * (s.q_pc - s.q_pc.mean())) for s in sets])

    def mean_r2(self, x, y):
        """x, y: arrays of the same shape; returns the mean centred r^2 at each."""
        x = np.asarray(x, float)[..., None]
        y = np.asarray(y, float)[..., None]
        a = self.rm - x
        b = self.qm - y
        sxx = self.srr + self.n * a * a
        sxy = self.srq + self.n * a * b
        syy = self.sqq + self.n * b * b
        ss_res = syy - sxy * sxy / sxx
        return np.mean(1 - ss_res / self.sqq, axis=-1)


def convergence_point(sets: list[DataSet], x_range=(-20000.0, None), tol_x=1.0, tol_y=100.0, y_range=None):
    """(x*, y*, mean r^2) maximising the mean centred r^2 of the Q-Rp lines through it.

    Each line's slope is closed-form for a given point, so the objective is a
    cheap function of (x*, y*): a coarse grid over the whole plausible region,
    then grids zooming in around the best cell until the cell is below tol_x
    ohm and tol_y pC (defaults: 1 ohm, 0.1 nC)."""
    mo = _Moments(sets)
    rp_min = min(float(s.rp_ohm.min()) for s in sets)
    q_max = max(float(s.q_pc.max()) for s in sets)
    x_top = min(rp_min - 1.0, x_range[1]) if x_range[1] is not None else rp_min - 1.0
    x_lo, x_hi = x_range[0], x_top
    y_lo, y_hi = y_range if y_range is not None else (-q_max, q_max)
    y_bot, y_top = y_lo, y_hi
    nx = ny = 81
    best = None
    for _ in range(60):
        xs = np.linspace(x_lo, x_hi, nx)
        ys = np.linspace(y_lo, y_hi, ny)
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        f = mo.mean_r2(gx, gy)
        f = np.where(np.isfinite(f), f, -np.inf)
        k = np.unravel_index(np.argmax(f), f.shape)
        best = (float(gx[k]), float(gy[k]), float(f[k]))
        dx, dy = xs[1] - xs[0], ys[1] - ys[0]
        if dx <= tol_x and dy <= tol_y:
            break
        x_lo, x_hi = max(x_range[0], best[0] - 4 * dx), min(x_top, best[0] + 4 * dx)
        y_lo, y_hi = max(y_bot, best[1] - 4 * dy), min(y_top, best[1] + 4 * dy)
        nx = ny = 41
    return best


def wilcoxon_holm(groups: dict[str, list[float]], threshold=R2_THRESHOLD) -> dict[str, dict]:
    """One-tailed Wilcoxon signed-rank test of r^2 > threshold per group (normal
    approximation with continuity correction: the paper's Z = 2.75 for n = 10),
    Holm-Bonferroni corrected."""
    from scipy.stats import wilcoxon

    res = {}
    for g, v in groups.items():
        d = np.asarray(v) - threshold
        if len(d) < 2 or np.all(d == 0):
            res[g] = {"n": len(d), "z": None, "p": 1.0}  # no test possible (JSON null, "-" in tables)
            continue
        w = wilcoxon(d, alternative="greater", method="approx", correction=True)
        res[g] = {"n": len(d), "z": float(w.zstatistic), "p": float(w.pvalue)}
    order = sorted(res, key=lambda g: res[g]["p"])
    m, running = len(order), 0.0
    for rank, g in enumerate(order):
        running = max(running, min(1.0, (m - rank) * res[g]["p"]))
        res[g]["p_holm"] = running
        res[g]["significant"] = running < 0.05
    return res


@dataclass
class FitResult:
    x_star_ohm: float
    y_star_pc: float
    mean_r2_q: float
    mean_r2_ep: float
    n_sets: int
    per_set: list[dict] = field(default_factory=list)
    by_condition: dict = field(default_factory=dict)

    def calibration(self) -> dict:
        return {"x_star_ohm": round(self.x_star_ohm), "y_star_pc": round(self.y_star_pc),
                "mean_r2_q": round(self.mean_r2_q, 4), "mean_r2_ep": round(self.mean_r2_ep, 4),
                "n_datasets": self.n_sets}


def _z(v) -> str:
    return f"{v:6.2f}" if v is not None else f"{'-':>6}"


def fit(sets: list[DataSet], device_range: bool = False) -> FitResult:
    """device_range: search only where the device accepts the point (-20 kohm <= x* <= 0, 0 <= y* < every Q)."""
    if device_range:
        q_min = min(float(s.q_pc.min()) for s in sets)
        x, y, mr2 = convergence_point(sets, x_range=(-20000.0, 0.0), y_range=(0.0, q_min - 1.0))
    else:
        x, y, mr2 = convergence_point(sets)
    per, by_q, by_e = [], {}, {}
    for s in sets:
        rp, ep, q = s.rp_ohm, s.ep_erg, s.q_pc
        me_slope = float(rp @ ep / (rp @ rp))  # erg/ohm: mE = I^2 T
        r2e = r2_through_point(rp, ep, 0.0, 0.0)
        r2q = r2_through_point(rp, q, x, y)
        per.append({"participant": s.participant, "condition": s.condition, "n": len(rp),
                    "me_ua2us": me_slope / ERG_PER_OHM_UA2_US, "r2_ep": r2e, "r2_q": r2q})
        by_e.setdefault(s.condition, []).append(r2e)
        by_q.setdefault(s.condition, []).append(r2q)
    stats_e, stats_q = wilcoxon_holm(by_e), wilcoxon_holm(by_q)
    by = {c: {"n": len(by_q[c]), "mean_r2_ep": float(np.mean(by_e[c])), "mean_r2_q": float(np.mean(by_q[c])),
              "ep": stats_e[c], "q": stats_q[c]} for c in by_q}
    res = FitResult(x, y, float(np.mean([p["r2_q"] for p in per])), float(np.mean([p["r2_ep"] for p in per])),
                    len(sets), per, by)
    _check_finite(res.__dict__, "fit")
    return res


def _check_finite(obj, where):
    from .files import FileProblem, finite

    try:
        finite(obj, where)
    except FileProblem as e:
        raise DataError(str(e)) from None


def validate(sets: list[DataSet], x_star_ohm: float, y_star_pc: float) -> dict:
    """Exp. 2: r^2 of the chosen points against the controller's lines from each trial's initial point."""
    by_q, by_e, per = {}, {}, []
    for s in sets:
        k = s.initial
        i0, t0, rp0 = s.i_ua[k], s.t_us[k], s.rp_ohm[k]
        me = i0 * i0 * t0
        mq = (i0 * t0 - y_star_pc) / (rp0 - x_star_ohm)
        r2e = r2_of_line(s.rp_ohm, s.ep_erg, me * ERG_PER_OHM_UA2_US, 0.0, 0.0)
        r2q = r2_of_line(s.rp_ohm, s.q_pc, mq, x_star_ohm, y_star_pc)
        per.append({"participant": s.participant, "condition": s.condition, "trial": s.trial, "r2_ep": r2e, "r2_q": r2q})
        by_e.setdefault(s.condition, []).append(r2e)
        by_q.setdefault(s.condition, []).append(r2q)
    se, sq = wilcoxon_holm(by_e), wilcoxon_holm(by_q)
    out = {"mean_r2_ep": float(np.mean([p["r2_ep"] for p in per])), "mean_r2_q": float(np.mean([p["r2_q"] for p in per])),
            "per_trial": per,
            "by_condition": {c: {"n": len(by_q[c]), "mean_r2_ep": float(np.mean(by_e[c])),
                                 "mean_r2_q": float(np.mean(by_q[c])), "ep": se[c], "q": sq[c]} for c in by_q}}
    _check_finite(out, "validate")
    return out


def table(res: FitResult) -> list[str]:
    """A table like the paper's Fig. 2I: per condition, mean r^2 and the one-tailed test of r^2 > 0.7."""
    head = (f"{'condition':<24} {'n':>3} | {'Ep-Rp r2':>8} {'Z':>6} {'p (Holm)':>9} | {'Q-Rp r2':>8} {'Z':>6} {'p (Holm)':>9}")
    lines = [head, "-" * len(head)]
    for c, v in sorted(res.by_condition.items()):
        e, q = v["ep"], v["q"]
        lines.append(f"{c:<24} {v['n']:>3} | {v['mean_r2_ep']:8.3f} {_z(e['z'])} {e['p_holm']:9.4f} | "
                     f"{v['mean_r2_q']:8.3f} {_z(q['z'])} {q['p_holm']:9.4f}")
    return lines


def figure(sets: list[DataSet], res: FitResult, out: Path | str) -> Path:
    from .plot import pyplot, save

    plt = pyplot()

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6))
    x, y = res.x_star_ohm, res.y_star_pc
    for s in sets:
        rp = s.rp_ohm / 1e3
        (h,) = ax[0].plot(rp, s.ep_erg, "o", ms=2, alpha=0.6)
        g = np.array([0, rp.max()])
        ax[0].plot(g, g * (s.rp_ohm @ s.ep_erg / (s.rp_ohm @ s.rp_ohm)) * 1e3, "-", lw=0.5, color=h.get_color())
        ax[1].plot(rp, s.q_pc / 1e6, "o", ms=2, alpha=0.6, color=h.get_color())
        dx, dy = s.rp_ohm - x, s.q_pc - y
        m = dx @ dy / (dx @ dx)
        g2 = np.array([x, s.rp_ohm.max()])
        ax[1].plot(g2 / 1e3, (y + m * (g2 - x)) / 1e6, "-", lw=0.5, color=h.get_color())
    ax[1].plot([x / 1e3], [y / 1e6], "k*", ms=10, label=f"(x*, y*) = ({x / 1e3:.2f} kΩ, {y / 1e6:.3f} µC)")
    ax[0].set(xlabel="Rp (kΩ)", ylabel="Ep (erg)", title=f"Ep–Rp, mean r² {res.mean_r2_ep:.3f}")
    ax[1].set(xlabel="Rp (kΩ)", ylabel="Q (µC)", title=f"Q–Rp, mean r² {res.mean_r2_q:.3f}")
    ax[1].legend(fontsize=8)
    conds = sorted(res.by_condition)
    data_e = [[p["r2_ep"] for p in res.per_set if p["condition"] == c] for c in conds]
    data_q = [[p["r2_q"] for p in res.per_set if p["condition"] == c] for c in conds]
    pos = np.arange(len(conds))
    ax[2].boxplot(data_e, positions=pos - 0.18, widths=0.3)
    ax[2].boxplot(data_q, positions=pos + 0.18, widths=0.3)
    ax[2].axhline(R2_THRESHOLD, color="r", lw=0.8, ls="--")
    ax[2].set_xticks(pos, conds, rotation=35, ha="right", fontsize=7)
    ax[2].set(ylabel="r² (left Ep, right Q)", title="r² per condition")
    return save(fig, out, ax)
