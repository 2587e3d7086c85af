"""Frame time of the firmware in the MicroPython unix VM (median, p99) and
allocation per frame, with a null board (the hardware returns at once with a
fixed captured pulse), so the figures are the firmware's own cost.

Run: .venv/bin/python bench/frame.py [--frames 20000] [--channels 2]
"""

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent

SCRIPT = """
import micropython, time
from array import array
import board_config as cfg, hid_protocol as hp, sensation_core as sc, stim

class NullBoard:
    def __init__(self, n):
        self.n_channels = n
        self.adc = [array("H", [1100 + (k % 7) for k in range(200)]) for _ in range(n)]
        self.sent = 0
    def set_amplitude(self, ch, i): return i
    def stop(self, ch): pass
    def feed_watchdog(self): pass
    def fire(self, ch, t): return t // 10
    def send(self, b): self.sent += 1
    def recv(self, b): return False

class Clock:
    ticks_us = time.ticks_us
    ticks_add = time.ticks_add
    ticks_diff = time.ticks_diff
    def sleep_us(self, us): pass

N = NFRAMES
CH = NCH
board = NullBoard(CH)
s = stim.Stimulator(board, Clock(), cfg, CH, 100)
b = bytearray(64)
for rep in (hp.cmd_calibrate(b, hp.CH_ALL, 1000, 1000, -1670, 186000), hp.cmd_arm(bytearray(64), hp.CH_ALL)):
    assert s.handle(rep, 0) == 0
s.sync_outputs()
dt = array("i", [0] * N)

def go():
    k = 0
    while k < N:
        t = time.ticks_us()
        s.frame(t)
        dt[k] = time.ticks_diff(time.ticks_us(), t)
        k += 1

import gc
go()  # warm up
gc.collect()
gc.disable()  # nothing is reclaimed while we watch
a0 = gc.mem_alloc()
m0 = micropython.mem_total()
go()
m1 = micropython.mem_total()
a1 = gc.mem_alloc()
gc.enable()
v = sorted(dt)
print(v[N // 2], v[N * 99 // 100], v[-1], (a1 - a0) / N, (m1 - m0) / N, s.errors)
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20000)
    ap.add_argument("--channels", type=int, default=2)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        Path(d, "b.py").write_text(SCRIPT.replace("NFRAMES", str(a.frames)).replace("NCH", str(a.channels)))
        env = dict(os.environ, MICROPYPATH=f"{ROOT / 'shared'}:{ROOT / 'firmware'}")
        out = subprocess.run([str(BIN / "micropython"), f"{d}/b.py"], capture_output=True, text=True, env=env)
    if out.returncode:
        sys.exit(out.stderr)
    med, p99, mx, kept, transient, errors = out.stdout.split()
    print(f"frames {a.frames}, channels {a.channels}, MicroPython unix VM (x86-64)")
    print("| frame time median | p99 | max | heap kept per frame (gc off) | transient code-state bytes per frame | firmware errors |")
    print("|---|---|---|---|---|---|")
    print(f"| {med} us | {p99} us | {mx} us | {float(kept):.0f} | {float(transient):.0f} | {errors} |")


if __name__ == "__main__":
    main()
