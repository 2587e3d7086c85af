"""A simulated participant doing the method of adjustment (docs/calibration.md).

Equal-intensity current at each duration follows a strength-duration law,
I(T) = K * l * site * (A / 5.6 cm^2) * (T / 1 ms)^(-a) * (1 + u) * (1 + e):
K ~ 1.6 mA lognormal(0.2) per person, a ~ N(0.5, 0.02), l = 1 ("weak") or 1.8
("strong"), site = exp(0.2 z), u = +0.05 (the bias toward the upper bound of
the equal-feeling range the paper describes), e ~ N(0, 0.03) adjustment error.

Each condition has its own skin (the simulator's electrode with rho lognormal
0.3, c lognormal 0.1), which sets Rp at the condition's first (reference)
point. The ground truth of the paper's model is built in: the skin's Rp at
every other equal-intensity point lies on the Q-Rp line through that reference
point and the true (x*, y*), plus measurement noise (Vp averaged over 10 pulses:
1 % by default). So `fit` can be checked for recovering (x*, y*).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .simrun import firmware_module

T_STEPS_US = np.arange(200, 701, 50)  # the paper's Exp. 1: 200..700 us in 50 us steps (11 points)
RP_FLOOR_OHM = 1000.0  # below any electrode's pulse resistance (Rs alone is 0.3-1.5 kohm)
REDRAWS = 100
CONDITIONS = [(m, site, area) for m in ("weak", "strong") for site in ("forearm", "upperarm") for area in (5.6, 3.0)]


def _electrode_cls():
    return firmware_module("sim_electrode").Electrode


@dataclass
class Person:
    k_ma: float
    a: float
    u: float = 0.05
    noise: float = 0.03


class SimParticipant:
    def __init__(self, seed=1, x_star_ohm=-1670.0, y_star_pc=186000.0, rp_noise=0.01):
        self.rng = np.random.default_rng(seed)
        self.x_star = x_star_ohm
        self.y_star = y_star_pc
        self.rp_noise = rp_noise
        self.Electrode = _electrode_cls()

    def person(self) -> Person:
        return Person(1.6 * float(np.exp(self.rng.normal(0, 0.2))), float(self.rng.normal(0.5, 0.02)))

    def matched_current_ua(self, p: Person, t_us, level, site, area):
        """The current (uA) this person sets at duration t_us to match the reference."""
        e = self.rng.normal(0, p.noise, np.shape(t_us))
        return 1000 * p.k_ma * level * site * (area / 5.6) * (np.asarray(t_us) / 1000.0) ** (-p.a) * (1 + p.u) * (1 + e)

    def skin(self, area):
        return self.Electrode(area_cm2=area, rho_ref=180.0 * float(np.exp(self.rng.normal(0, 0.3))),
                              c_nf_cm2=2.5 * float(np.exp(self.rng.normal(0, 0.1))))

    def rp_on_line(self, q_pc, q_ref, rp_ref):
        """Rp at charge q on the Q-Rp line through the reference point and (x*, y*), with noise."""
        mq = (q_ref - self.y_star) / (rp_ref - self.x_star)
        rp = self.x_star + (q_pc - self.y_star) / mq
        return rp * (1 + self.rng.normal(0, self.rp_noise, np.shape(q_pc)))

    def exp1_rows(self, n_participants=10):
        rows = []
        for pi in range(n_participants):
            p = self.person()
            sites = {"forearm": 1.0, "upperarm": float(np.exp(0.2 * self.rng.normal()))}
            for ci, (mag, site, area) in enumerate(CONDITIONS):
                level = 1.0 if mag == "weak" else 1.8
                for _ in range(REDRAWS):
                    i = self.matched_current_ua(p, T_STEPS_US, level, sites[site], area)
                    i = np.maximum(i, 50.0)
                    skin = self.skin(area)
                    rp_ref = skin.rp_kohm(float(i[0]), float(T_STEPS_US[0])) * 1000.0
                    q = i * T_STEPS_US
                    rp = self.rp_on_line(q, q[0], rp_ref)
                    rp[0] = rp_ref * (1 + self.rng.normal(0, self.rp_noise))
                    if rp.min() >= RP_FLOOR_OHM:  # the line is a model of the measured range only: far out
                        break  # (a large charge, a steep line) it reaches 0 ohm; such a draw is drawn again
                else:
                    raise RuntimeError(f"P{pi + 1:02d}: no plausible skin in {REDRAWS} draws")
                for t, ii, r in zip(T_STEPS_US, i, rp):
                    rows.append({"participant": f"P{pi + 1:02d}", "condition": f"{mag}-{site}-{area:g}cm2",
                                 "t_us": int(t), "i_ua": round(float(ii), 1), "rp_ohm": round(float(r), 1)})
        return rows

    def exp2_rows(self, n_participants=10, trials=2, points=8, t0_us=1000):
        """Exp. 2 (gel): from an initial point at T0, the participant's equal-intensity
        points as gel lowers Rp by up to ~40 kohm; one condition per magnitude/site."""
        rows = []
        for pi in range(n_participants):
            p = self.person()
            for ci, (mag, site, area) in enumerate(CONDITIONS[:5]):
                level = 1.0 if mag == "weak" else 1.8
                for tr in range(trials):
                    i0 = float(self.matched_current_ua(p, t0_us, level, 1.0, area))
                    rp0 = self.skin(area).rp_kohm(i0, t0_us) * 1000.0
                    me, q0 = i0 * i0 * t0_us, i0 * t0_us
                    mq = (q0 - self.y_star) / (rp0 - self.x_star)
                    cond = f"{mag}-{site}-{area:g}cm2"
                    rows.append({"participant": f"P{pi + 1:02d}", "condition": cond, "trial": tr + 1, "initial": 1,
                                 "t_us": t0_us, "i_ua": round(i0, 1), "rp_ohm": round(rp0, 1)})
                    for rp_true in np.linspace(rp0 * 0.9, max(rp0 * 0.3, 3000.0), points):
                        q = mq * (rp_true - self.x_star) + self.y_star
                        t = q * q / me
                        ii = me / q * (1 + self.rng.normal(0, p.noise))  # the participant's adjustment of I at that T
                        rp = rp_true * (1 + self.rng.normal(0, self.rp_noise))
                        rows.append({"participant": f"P{pi + 1:02d}", "condition": cond, "trial": tr + 1, "initial": 0,
                                     "t_us": round(float(t), 1), "i_ua": round(float(ii), 1), "rp_ohm": round(float(rp), 1)})
        return rows


def write_rows(path: Path | str, rows: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
