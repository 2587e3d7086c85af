"""Figures from recordings: the paper's Fig. 5 layout (Rp, I, T, mE, mQ over
time; controller and open loop side by side), and the Ep-Rp / Q-Rp planes with
the constant-sensation lines."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .record import meta_int


def pyplot():
    """matplotlib's pyplot on the file-only Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, out: Path | str, axes=()) -> Path:
    """Grid the axes, lay out, write the PNG and free the figure."""
    for a in axes:
        a.grid(alpha=0.3)
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=110)
    fig.clf()
    import matplotlib.pyplot as plt

    plt.close(fig)
    return out


def _series(rows, channel=0):
    r = [x for x in rows if x["channel"] == channel and x["i_ua"] > 0]
    f = {k: np.array([x[k] for x in r], dtype=float) for k in r[0]} if r else {}
    return f


def fig5(recordings: list[tuple[str, dict, list[dict]]], out: Path | str, channel: int = 0) -> Path:
    """recordings: (title, meta, rows) per column, e.g. controller and open loop."""
    plt = pyplot()

    n = len(recordings)
    fig, axes = plt.subplots(5, n, figsize=(5.5 * n, 10), sharex="col", squeeze=False)
    ylabels = ["Rp (kΩ)", "I (mA)", "T (µs)", "mE (mA²·ms)", "mQ (µC/kΩ)"]
    for col, (title, meta, rows) in enumerate(recordings):
        s = _series(rows, channel)
        if not s:
            continue
        t = (s["time_us"] - s["time_us"][0]) / 1e6
        ax = axes[:, col]
        ax[0].plot(t, s["rp_ohm"] / 1e3, color="k", lw=1)
        ax[1].plot(t, s["i_ua"] / 1e3, color="tab:blue", lw=1)
        ax[2].plot(t, s["t_us"], color="tab:orange", lw=1)
        ax[3].plot(t, s["i_ua"] ** 2 * s["t_us"] / 1e9, color="tab:green", lw=1, label="I²T of the pulse")
        ax[3].plot(t, s["me_ua2ms"] / 1e6, color="tab:green", ls="--", lw=1, label="calibrated mE")
        ax[4].plot(t, s["mq_last_fc_per_ohm"] / 1e6, color="tab:red", lw=1, label="measured")
        ax[4].plot(t, s["mq_target_fc_per_ohm"] / 1e6, color="tab:red", ls="--", lw=1, label="target")
        ax[0].set_title(title)
        ax[-1].set_xlabel("time (s)")
        lo, hi = np.percentile(s["mq_target_fc_per_ohm"] / 1e6, [0, 100])
        ax[4].set_ylim(min(lo * 0.4, np.percentile(s["mq_last_fc_per_ohm"] / 1e6, 1)), hi * 1.4)
        ax[3].set_ylim(0, 2 * max(1e-9, np.median(s["me_ua2ms"] / 1e6)))
        for a in ax:
            a.grid(alpha=0.3)
        ax[3].legend(loc="upper right", fontsize=7)
        ax[4].legend(loc="upper right", fontsize=7)
    for k, lab in enumerate(ylabels):
        axes[k, 0].set_ylabel(lab)
    fig.suptitle(f"steadytouch: {recordings[0][1].get('scenario', '')} (channel {channel})")
    return save(fig, out)


def planes(meta: dict, rows: list[dict], out: Path | str, channel: int = 0) -> Path:
    """Ep-Rp and Q-Rp planes of the delivered pulses with the calibrated lines."""
    plt = pyplot()

    s = _series(rows, channel)
    rp = s["rp_ohm"] / 1e3  # kΩ
    i_ma, t_ms = s["i_ua"] / 1e3, s["t_us"] / 1e3
    ep = rp * i_ma**2 * t_ms * 10.0  # kΩ·mA²·ms = 1e-6 J = 10 erg
    q = i_ma * t_ms  # µC
    me = np.median(s["me_ua2ms"]) / 1e6  # mA²·ms
    x = meta_int(meta, "x_star_ohm") / 1e3 if "x_star_ohm" in meta else None
    y = meta_int(meta, "y_star_pc") / 1e6 if "y_star_pc" in meta else None
    mq = np.median(s["mq_target_fc_per_ohm"]) / 1e6  # µC/kΩ
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.5))
    grid = np.linspace(0, rp.max() * 1.1, 50)
    a.scatter(rp, ep, s=4, alpha=0.5)
    a.plot(grid, grid * me * 10.0, "k--", lw=1, label="Ep = mE·Rp (constant sensation)")
    a.set_xlabel("Rp (kΩ)")
    a.set_ylabel("Ep (erg)")
    a.legend(fontsize=8)
    b.scatter(rp, q, s=4, alpha=0.5, color="tab:red")
    if x is not None and y is not None:
        g2 = np.linspace(x, rp.max() * 1.1, 50)
        b.plot(g2, mq * (g2 - x) + y, "k--", lw=1, label=f"Q = mQ·(Rp − x*) + y*, (x*, y*) = ({x:.2f} kΩ, {y:.3f} µC)")
        b.plot([x], [y], "ko", ms=4)
    b.set_xlabel("Rp (kΩ)")
    b.set_ylabel("Q (µC)")
    b.legend(fontsize=8)
    return save(fig, out, (a, b))
