"""Fuzz the firmware's command handler with millions of OUT reports (tests/mp_fuzz.py in
the MicroPython VM, one process per core, consecutive seeds).

    .venv/bin/python bench/fuzz.py --reports 1000000 [--jobs 2] [--seed 1]

Prints one line per batch and a summary: reports, pulses checked, results by code,
failures (with the seed that replays each: micropython tests/mp_fuzz.py SEED N).
Figures: docs/safety.md."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BATCH = 50_000


def run(mp: str, seed: int, n: int):
    env = dict(os.environ, MICROPYPATH=os.pathsep.join([str(ROOT / "shared"), str(ROOT / "firmware")]))
    p = subprocess.run([mp, str(ROOT / "tests" / "mp_fuzz.py"), str(seed), str(n)], capture_output=True, text=True,
                       env=env)
    last = (p.stdout.strip().splitlines() or ["FAIL no output " + p.stderr[-300:]])[-1]
    return seed, n, p.returncode, last


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reports", type=int, default=1_000_000)
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    if a.reports < 1 or a.jobs < 1:
        ap.error("--reports and --jobs must be >= 1")
    mp = str(Path(sys.executable).parent / "micropython")
    batches = [(a.seed + k, min(BATCH, a.reports - k * BATCH)) for k in range((a.reports + BATCH - 1) // BATCH)]
    t0 = time.monotonic()
    total, pulses, fails, results = 0, 0, [], {}
    with ThreadPoolExecutor(a.jobs) as ex:
        for seed, n, rc, last in ex.map(lambda b: run(mp, *b), batches):
            print(f"seed {seed}: {last}", flush=True)
            if rc or not last.startswith("OK"):
                fails.append((seed, n, last))
                continue
            total += n
            pulses += int(last.split("pulses=")[1].split()[0])
            for kv in last.split("results=")[1].split(","):
                k, v = kv.split(":")
                results[int(k)] = results.get(int(k), 0) + int(v)
    dt = time.monotonic() - t0
    print(f"\n{total} reports in {dt:.0f} s ({a.jobs} jobs), {pulses} pulses checked, results by code "
          + ", ".join(f"{k}: {v}" for k, v in sorted(results.items())) + f"; {len(fails)} failed batches")
    for seed, n, last in fails:
        print(f"  FAILED seed {seed} ({n} reports): {last}  -> replay: micropython tests/mp_fuzz.py {seed} {n}")
    return 1 if fails else 0


if __name__ == "__main__":
    sys.exit(main())
