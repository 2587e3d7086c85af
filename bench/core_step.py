"""ns per Controller.update(): MicroPython VM (.mpy), CPython, and a naive float law in MicroPython;
and MODE_FAST with a skin model in MicroPython (mean and worst single update).

Run: .venv/bin/python bench/core_step.py [--n 20000]
Prints a markdown table (paste into docs/performance.md with this command).
"""

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import timeit
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
sys.path.insert(0, str(ROOT / "shared"))
import sensation_core as sc  # noqa: E402
from steadytouch.simrun import native_march  # noqa: E402

MP_SCRIPT = """
import time, sensation_core as sc

def rps(n):
    # the same pseudo-random walk over 3..123 kohm on every run
    return [3000 + (k * 7919) % 120000 for k in range(n)]

def bench_core(rp_list):
    c = sc.Controller(500, 20000, 50, 2000, 20000000)
    c.calibrate(1000, 1000, 30000, -1670, 186000)
    t = time.ticks_us()
    for rp in rp_list:
        c.update(rp)
    return time.ticks_diff(time.ticks_us(), t)

class FloatLaw:
    # Eqs. 1-4 written naively with floats (no bounds, no checks)
    def __init__(self, i0, t0, rp0, x, y):
        self.me = i0 * i0 * t0 * 1.0
        self.mq = (i0 * t0 - y) / (rp0 - x)
        self.x = x
        self.y = y
    def update(self, rp):
        q = self.mq * (rp - self.x) + self.y
        self.i = self.me / q
        self.t = q * q / self.me

def bench_float(rp_list):
    c = FloatLaw(1000, 1000, 30000, -1670, 186000)
    t = time.ticks_us()
    for rp in rp_list:
        c.update(rp)
    return time.ticks_diff(time.ticks_us(), t)

def bench_model(rp_list):
    # MODE_FAST with a skin model: on this walk nearly every update is a model jump
    c = sc.Controller(500, 20000, 50, 2000, 20000000)
    c.calibrate(1000, 1000, 30000, -1670, 186000)
    c.set_mode(sc.MODE_FAST)
    c.set_skin(500, 36045, 14000)
    worst = 0
    t = time.ticks_us()
    for rp in rp_list:
        t1 = time.ticks_us()
        c.update(rp)
        d = time.ticks_diff(time.ticks_us(), t1)
        if d > worst:
            worst = d
    return time.ticks_diff(time.ticks_us(), t), worst, c.model_jumps

def bench_empty(rp_list):
    t = time.ticks_us()
    for rp in rp_list:
        pass
    return time.ticks_diff(time.ticks_us(), t)

N = NN_PLACEHOLDER
r = rps(N)
best = [10**9, 10**9, 10**9]
for _ in range(5):
    best[0] = min(best[0], bench_core(r))
    best[1] = min(best[1], bench_float(r))
    best[2] = min(best[2], bench_empty(r))
m = bench_model(r)
for _ in range(4):
    m2 = bench_model(r)
    if m2[0] < m[0]:
        m = m2
print(best[0], best[1], best[2], m[0], m[1], m[2])
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000, help="updates per timing run (default 20000)")
    n = ap.parse_args().n
    with tempfile.TemporaryDirectory() as d:
        for m in ("sensation_core", "fixmath", "fast_step", "skin_tau", "skin_model"):  # the core and its modules
            subprocess.run([str(BIN / "mpy-cross"), f"-march={native_march()}", "-o", f"{d}/{m}.mpy", str(ROOT / f"shared/{m}.py")],
                           check=True)  # -march: the core has viper functions
        Path(d, "b.py").write_text(MP_SCRIPT.replace("NN_PLACEHOLDER", str(n)))
        env = dict(os.environ, MICROPYPATH=d)
        out = subprocess.run([str(BIN / "micropython"), f"{d}/b.py"], capture_output=True, text=True, env=env, check=True)
    core_us, float_us, empty_us, model_us, model_worst_us, model_jumps = map(int, out.stdout.split())
    c = sc.Controller(500, 20000, 50, 2000, 20000000)
    c.calibrate(1000, 1000, 30000, -1670, 186000)
    rps = [3000 + (k * 7919) % 120000 for k in range(n)]

    def run():
        for rp in rps:
            c.update(rp)

    cp = min(timeit.repeat(run, number=1, repeat=5)) / n * 1e9
    print(f"machine: {platform.machine()} {platform.processor() or ''} python {platform.python_version()}")
    print("| implementation | ns per update |")
    print("|---|---|")
    print(f"| sensation_core (.mpy) in MicroPython unix VM | {(core_us - empty_us) * 1000 / n:.0f} |")
    print(f"| naive float law in MicroPython unix VM | {(float_us - empty_us) * 1000 / n:.0f} |")
    print(f"| sensation_core in CPython {platform.python_version()} | {cp:.0f} |")
    print(f"| MODE_FAST with a skin model (.mpy) in MicroPython unix VM: mean / worst single update | "
          f"{model_us * 1000 / n:.0f} / {model_worst_us * 1000:.0f} ({model_jumps} of {n} updates were model jumps) |")
    print(f"(loop overhead subtracted for MicroPython: {empty_us * 1000 / n:.0f} ns; best of 5 runs of {n})")


if __name__ == "__main__":
    main()
