"""The clock mapping's residual on this machine: `record --lsl` against the firmware
in the VM in real time (sim://, 4 channels, 50 Hz), for --seconds; prints the fit
(offset, drift, residual of the per-second minima around the line) of each run.
The VM's clock is this machine's, so the drift is ~0: what shows is the spread of
the least transport delay (pipe, reader thread, the host loop).

Run: .venv/bin/python bench/lsl_clock.py [--seconds 60] [--runs 3]
"""

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--runs", type=int, default=3)
    a = ap.parse_args()
    env = dict(os.environ, LSLAPICFG=str(ROOT / "host" / "lsl" / "loopback.cfg"))
    exe = Path(sys.executable).parent / "steadytouch"
    with tempfile.TemporaryDirectory() as tmp:
        scen = Path(tmp) / "steady-long.csv"
        scen.write_text(f"time_s,contact,hydration\n0,1,1\n{a.seconds + 10:.0f},1,1\n")
        for k in range(a.runs):
            r = subprocess.run([str(exe), "record", str(Path(tmp) / f"r{k}.csv"), "--lsl", "--seconds", str(a.seconds),
                                "--device", f"sim://{scen}?channels=4&auto=1000,1000,-1670,186000"],
                               capture_output=True, text=True, env=env, timeout=a.seconds + 60)
            m = re.search(r"LSL: (\d+) samples .*\((offset_s=\S+ drift_ppm=\S+ residual_us=\S+ reports=\d+ arrival_late_us_mean=\d+ arrival_late_us_max=\d+)\)", r.stdout)
            print(f"run {k + 1}: " + (f"{m.group(1)} samples, {m.group(2)}" if m else f"failed: {r.stderr.strip()}"))


if __name__ == "__main__":
    main()
