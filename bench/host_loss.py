"""Host loss: how long a simulated device stimulates after its host is gone.

Run: .venv/bin/python bench/host_loss.py [--n 10]

Three ways a host can be lost, each measured --n times against sim:// (the
firmware in the MicroPython VM, real-time clock, 2 channels armed with --auto):

- sigkill: `steadytouch record` is SIGKILLed; time until the VM child process
  is gone (the kernel kills it with its parent: PR_SET_PDEATHSIG), and the last
  pulse the recording got before the kill.
- eof: the VM alone (no PDEATHSIG), its stdin closed as when a host dies;
  time until its last pulse report reaches us and until it exits
  (--exit-on-eof: every channel stopped within a frame).
- silent: the host stays connected but stops talking (a stalled loop; on a
  board this is also USB unplugged or a hung host). Only the firmware's
  keep-alive guards it: the gap, in device time, between the host's last
  command and the device's last pulse, for the default 1000 ms timeout.
Figures go into docs/safety.md.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT / "shared")]
EXE = str(Path(sys.executable).parent / "steadytouch")
AUTO = "1000,1000,-1670,186000"


def children(pid):
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def alive(pid):
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def sigkill_once(tmp: Path) -> float:
    out = tmp / "rec.csv"
    p = subprocess.Popen([EXE, "record", str(out), "--device", f"sim://steady?auto={AUTO}"], cwd=ROOT,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t_end = time.time() + 30
    while time.time() < t_end and not (children(p.pid) and out.exists() and out.stat().st_size > 3000):
        time.sleep(0.02)
    kids = children(p.pid)
    time.sleep(0.5)
    t0 = time.monotonic()
    p.kill()
    p.wait()
    while any(alive(k) for k in kids) and time.monotonic() - t0 < 60:
        time.sleep(0.001)
    return time.monotonic() - t0


def eof_once() -> tuple[float, float]:
    from steadytouch.protocol import Telemetry, decode, split_stdio_stream
    from steadytouch.simrun import FIRMWARE, SHARED, micropython_exe

    env = dict(os.environ, MICROPYPATH=os.pathsep.join([str(SHARED), str(FIRMWARE)]))
    p = subprocess.Popen([micropython_exe(), str(FIRMWARE / "main.py"), "--scenario", "steady", "--realtime",
                          "--exit-on-eof", "--auto", AUTO], stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
    os.set_blocking(p.stdout.fileno(), False)
    buf, t0, last_pulse = b"", None, None
    start = time.monotonic()
    while True:
        chunk = p.stdout.read(65536)
        now = time.monotonic()
        if chunk:
            buf += chunk
            reps = split_stdio_stream(buf)
            buf = buf[66 * len(reps):] if reps else buf
            if t0 is not None and any(isinstance(r, Telemetry) and r.i_ua for r in map(decode, reps)):
                last_pulse = now
        elif chunk == b"" and p.poll() is not None:
            break
        if t0 is None and now - start > 1.0:
            p.stdin.close()  # the host is gone
            t0 = time.monotonic()
        time.sleep(0.001)
    exit_s = time.monotonic() - t0
    return (last_pulse - t0 if last_pulse else 0.0), exit_s


def silent_once(timeout_ms=1000) -> float:
    from steadytouch.device import Device
    from steadytouch.protocol import Telemetry
    from steadytouch.transport import open_transport

    import hid_protocol as hp

    with open_transport(f"sim://steady?auto={AUTO}") as t:
        d = Device(t)
        d.keep_alive(timeout_ms)
        time.sleep(0.3)
        last = d.keepalive(timeout_ms)
        time.sleep(timeout_ms / 1000 + 0.3)
        reps = []
        while len(reps) < 2000 and not any(isinstance(r, Telemetry) and r.stop == hp.STOP_KEEPALIVE for r in reps[:-5]):
            reps.append(d._decode(t.read(2.0)))
        pulses = [r for r in reps if isinstance(r, Telemetry) and r.i_ua > 0]
        return (pulses[-1].time_us - last.time_us) % (1 << 30) / 1000


def summary(name, xs, unit="ms"):
    return (f"| {name} | {len(xs)} | {statistics.median(xs):.0f} {unit} | {max(xs):.0f} {unit} |")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=10)
    a = ap.parse_args()
    kill, eof_pulse, eof_exit, silent = [], [], [], []
    with tempfile.TemporaryDirectory() as d:
        for _ in range(a.n):
            kill.append(sigkill_once(Path(d)) * 1000)
    for _ in range(a.n):
        lp, ex = eof_once()
        eof_pulse.append(lp * 1000)
        eof_exit.append(ex * 1000)
    for _ in range(a.n):
        silent.append(silent_once())
    print("| host loss | runs | median | worst |")
    print("|---|---|---|---|")
    print(summary("SIGKILL of `record` -> VM process gone (wall clock)", kill))
    print(summary("stdin closed -> last pulse report received (wall clock)", eof_pulse))
    print(summary("stdin closed -> VM exited (wall clock)", eof_exit))
    print(summary("host silent -> last pulse (device clock, keep-alive 1000 ms)", silent))


if __name__ == "__main__":
    signal.signal(signal.SIGINT, signal.default_int_handler)
    main()
