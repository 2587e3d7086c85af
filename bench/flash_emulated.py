"""Time each step of `steadytouch flash` on the emulated Pico.

Run: .venv/bin/python bench/flash_emulated.py [--runs 1]

Boots ../shared/emulator's real MicroPython v1.28.0 for the RP2040 in rp2040js,
served by host/emu (tests/flash/emu.py: its USB serial and its HID interface on
two TCP ports), then per run: flash a blank board, wait until the firmware runs
its loop, flash again onto the running board (nothing to copy). Step 8 reads
the version back over HID (emu+tcp://); --no-hid-check times the serial-REPL
fallback instead. Prints each step's wall time (from the moment its progress line
arrives) and the total. The emulator runs at 0.1-0.4x a real RP2040 and its
USB serial goes through a TCP socket, so a real Pico is faster; the split
between steps is what this shows. docs/performance.md quotes it.
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests" / "flash"))
import emu  # noqa: E402

NAMES = {1: "compile", 2: "libraries (host)", 3: "connect", 4: "error log", 5: "stored correction",
         6: "libraries on the board", 7: "firmware files", 8: "boot check"}  # flash.STEPS steps


def flash(pico, build: Path, hid: bool) -> tuple[float, dict[str, float], str]:
    t0 = time.monotonic()
    check = ["--device", pico.hid_url] if hid else ["--no-hid-check"]
    p = subprocess.Popen([str(Path(sys.executable).parent / "steadytouch"), "flash", "--port", pico.url, *check,
                          "--lib-dir",
                          str(emu.EMU / "board-lib"), "--build-dir", str(build), "--boot-timeout-s", "120"],
                         cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    steps, last, out = {}, 0.0, []
    for line in p.stdout:
        out.append(line)
        m = re.match(r"\[(\d)/%d\]" % len(NAMES), line)
        if m:
            t = time.monotonic() - t0
            steps[NAMES[int(m.group(1))]] = t - last
            last = t
    if p.wait():
        sys.exit("flash failed:\n" + "".join(out))
    return time.monotonic() - t0, steps, "".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--no-hid-check", action="store_true", help="time the serial-REPL readback instead of HID")
    a = ap.parse_args()
    if not emu.available():
        sys.exit(emu.SKIP_REASON)
    rows: dict[str, list[tuple[float, dict]]] = {"blank board": [], "running board, nothing changed": []}
    with tempfile.TemporaryDirectory() as d:
        for _ in range(a.runs):
            with emu.Pico(Path(d) / "emu.log", seconds=600) as pico:
                total, steps, out = flash(pico, Path(d) / "dev", not a.no_hid_check)
                rows["blank board"].append((total, steps))
                print(out)
                log = Path(d) / "emu.log"
                t_end = time.monotonic() + 120
                while "enumerating again" not in log.read_text().rsplit("hard reset", 1)[-1]:
                    if time.monotonic() > t_end:
                        sys.exit("the firmware did not start")
                    time.sleep(0.5)
                time.sleep(2)
                total, steps, out = flash(pico, Path(d) / "dev", not a.no_hid_check)
                rows["running board, nothing changed"].append((total, steps))
                print(out)
    print("| step | " + " | ".join(rows) + " |")
    print("| --- | " + " | ".join("---:" for _ in rows) + " |")
    for name in NAMES.values():
        cells = [f"{statistics.median(s[name] for _, s in r):.1f} s" for r in rows.values()]
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("| **total** | " + " | ".join(f"**{statistics.median(t for t, _ in r):.0f} s**" for r in rows.values())
          + " |")


if __name__ == "__main__":
    main()
