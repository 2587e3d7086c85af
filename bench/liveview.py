"""Is `monitor --plot` smooth at 4 channels x 100 Hz? Feeds the live view 400
telemetry reports per second in real time (as the monitor's loop does) and
redraws every 0.1 s, then redraws as fast as it can; reports redraws per second,
time per redraw and the CPU the process used. Agg always; the real window
(TkAgg) too when a display is set (e.g. `xvfb-run -a`).

Run: .venv/bin/python bench/liveview.py [--seconds 20]
     xvfb-run -a .venv/bin/python bench/liveview.py --window
"""

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "shared"))

import hid_protocol as hp  # noqa: E402
from steadytouch.liveview import LivePlot  # noqa: E402
from steadytouch.protocol import Telemetry  # noqa: E402


def tel(seq, f, ch):
    i = 1000 + 150 * ch + int(80 * np.sin(f / 20))
    mqt = 37563 + 400 * ch
    return Telemetry(seq, f * 10_000, ch, 0, 0, i, 1000, 3000, 20000 + int(3000 * np.sin(f / 40 + ch)),
                     i * i // 1000, mqt, mqt + int(40 * np.sin(f / 5)), 0, i, 1000, 0, 300, hp.FLAG_ARMED, 100)


def run(interactive: bool, seconds: float):
    lp = LivePlot(interactive=interactive)
    seq = f = 0
    # real time: 400 reports/s, a redraw every 0.1 s
    wall0, cpu0 = time.perf_counter(), time.process_time()
    draw_t = []
    next_draw = wall0
    while time.perf_counter() - wall0 < seconds:
        due = int((time.perf_counter() - wall0) * 100)
        while f < due:
            for ch in range(4):
                lp.add(tel(seq, f, ch))
                seq += 1
            f += 1
        now = time.perf_counter()
        if now >= next_draw:
            next_draw = now + 0.1
            t = time.perf_counter()
            lp.draw()
            draw_t.append(time.perf_counter() - t)
        time.sleep(0.002)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    behind = f - int(wall * 100)
    # flat out: the window full (10 s x 4 channels x 100 Hz), redraw back to back
    t0 = time.perf_counter()
    n = 0
    while time.perf_counter() - t0 < 3:
        lp.draw()
        n += 1
    flat = n / (time.perf_counter() - t0)
    lp.close()
    d = np.array(draw_t) * 1e3
    return {"backend": "TkAgg window" if interactive else "Agg", "redraws_per_s": len(draw_t) / wall,
            "draw_ms_median": float(np.median(d)), "draw_ms_p95": float(np.percentile(d, 95)),
            "cpu_percent": 100 * cpu / wall, "frames_behind": behind, "full_redraws": lp.full_draws,
            "flat_out_redraws_per_s": flat}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--window", action="store_true", help="also the real window (needs DISPLAY)")
    a = ap.parse_args()
    res = [run(False, a.seconds)]
    if a.window:
        if not os.environ.get("DISPLAY"):
            sys.exit("--window needs a display: run it under `xvfb-run -a` or on a desktop")
        res.append(run(True, a.seconds))
    print(f"4 channels x 100 Hz, {a.seconds:g} s in real time, a redraw every 0.1 s:")
    for r in res:
        print(f"  {r['backend']:<13} {r['redraws_per_s']:5.1f} redraws/s, draw {r['draw_ms_median']:5.1f} ms median "
              f"/ {r['draw_ms_p95']:5.1f} ms p95, CPU {r['cpu_percent']:4.0f} %, {r['full_redraws']} full redraws, "
              f"flat out {r['flat_out_redraws_per_s']:5.1f} redraws/s")


if __name__ == "__main__":
    main()
