"""Can the monitor keep up with 4 channels x 100 Hz? Feeds it real decoded
telemetry as fast as it takes it, redrawing 10 times per simulated second,
and reports the sustained rate against the 400 reports/s it needs.

Run: .venv/bin/python bench/monitor.py [--seconds 30]
"""

import argparse
import io
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "shared"))

import hid_protocol as hp  # noqa: E402
from steadytouch.device import Device  # noqa: E402
from steadytouch.monitor import MonitorState  # noqa: E402
from steadytouch.transport import Transport  # noqa: E402


class Replay(Transport):
    """Raw reports of 4 channels x 100 Hz, as a device would send them."""

    def __init__(self, seconds):
        self.reports = []
        b = bytearray(64)
        seq = 0
        for f in range(int(seconds * 100)):
            for ch in range(4):
                hp.clear(b)
                b[0] = hp.REP_TELEMETRY
                b[hp.O_CH] = ch
                hp.put_i32(b, hp.O_SEQ, seq)
                hp.put_i32(b, hp.O_TIME, f * 10000)
                hp.put_u16(b, hp.O_I, 1000 + ch)
                hp.put_u16(b, hp.O_T, 1000)
                hp.put_i32(b, hp.O_RP, 30000 + f % 50)
                b[hp.O_RATE] = 100
                self.reports.append(bytes(b))
                seq += 1
        self.k = 0

    def read(self, timeout_s):
        if self.k >= len(self.reports):
            return None
        self.k += 1
        return self.reports[self.k - 1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="simulated seconds of telemetry (default 30)")
    a = ap.parse_args()
    src = Replay(a.seconds)
    d = Device(src)
    st = MonitorState()
    screen = io.StringIO()
    n = 0
    draws = 0
    t0 = time.perf_counter()
    while True:
        rep = d.read(0)
        if rep is None:
            break
        st.add(rep)
        n += 1
        if n % 40 == 0:  # 10 screens per simulated second at 400 reports/s
            screen.write(st.render("bench", d.lost))
            draws += 1
    dt = time.perf_counter() - t0
    rate = n / dt
    print(f"{n} reports ({a.seconds:g} s of 4 channels x 100 Hz) decoded, folded and drawn {draws} times in {dt:.3f} s")
    print(f"sustained {rate:,.0f} reports/s = {rate / 400:.0f}x the 400 reports/s needed; "
          f"{dt / n * 1e6:.1f} us per report, lost {d.lost}")


if __name__ == "__main__":
    main()
