"""`steadytouch` command line."""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
import time
from pathlib import Path

import hid_protocol as hp
import sensation_core as sc

from . import __version__
from .protocol import STOP_WORDS, Telemetry
from .simrun import Calib, SimError, run_firmware, scenario_keys

TELEMETRY_COLUMNS = [
    "seq", "time_us", "channel", "i_ua", "t_us", "vp_mv", "rp_ohm", "status", "stop", "mode", "me_ua2ms",
    "mq_target_fc_per_ohm", "mq_last_fc_per_ohm", "next_i_ua", "next_t_us", "flags", "overruns", "loop_us",
]


def write_csv(path: Path, tel: list[Telemetry], meta: dict) -> None:
    with open(path, "w", newline="") as f:
        for k, v in meta.items():
            f.write(f"# {k}: {v}\n")
        w = csv.writer(f)
        w.writerow(TELEMETRY_COLUMNS)
        for t in tel:
            w.writerow([getattr(t, c) for c in TELEMETRY_COLUMNS])


def phase_table(keys, duration_s, runs: dict[str, list[Telemetry]]) -> list[str]:
    bounds = [k[0] for k in keys] + [duration_s]
    names = list(runs)
    head = f"{'phase (s)':>13} | {'contact':>7} | {'Rp range kohm':>15} | " + " | ".join(
        f"{'mQ err ' + n:>17}" for n in names)
    lines = [head, "-" * len(head)]
    ref = runs[names[0]]
    for k in range(len(bounds) - 1):
        lo, hi = bounds[k], bounds[k + 1]
        if hi - lo < 0.9:
            continue  # a ramp between two holds
        settled_from = lo + min(1.0, (hi - lo) / 2)  # judge the hold after it had time to settle
        cells = []
        for n in names:
            w = [t for t in runs[n] if settled_from <= t.time_us / 1e6 < hi and t.i_ua and t.channel == 0]
            if not w:
                cells.append(f"{'stopped':>17}")
                continue
            err = abs(statistics.median(t.mq_last_fc_per_ohm - t.mq_target_fc_per_ohm for t in w))
            rel = err / max(1, w[0].mq_target_fc_per_ohm)
            bound = " (bound)" if any(t.status & sc.ST_BOUND_MASK for t in w) else ""
            cells.append(f"{err / 1e6:9.2e}{bound:>8}" if bound else f"{err / 1e6:9.2e} {rel:6.1%} ")
        w = [t for t in ref if lo <= t.time_us / 1e6 < hi and t.i_ua and t.channel == 0]
        rp = f"{min(t.rp_ohm for t in w) / 1e3:6.1f}-{max(t.rp_ohm for t in w) / 1e3:6.1f}" if w else "-"
        lines.append(f"{lo:6.1f}-{hi:6.1f} | {keys[k][1]:7.2f} | {rp:>15} | " + " | ".join(cells))
    return lines


def cmd_sim(a) -> int:
    keys, duration = scenario_keys(a.scenario)
    cal = Calib(a.i0_ua, a.t0_us, a.x_star_ohm, a.y_star_pc)
    modes = ["akhtar", "open"] if a.mode == "both" else [a.mode]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = {}
    for m in modes:
        t0 = time.perf_counter()
        print(f"running {a.scenario} ({duration:.0f} s simulated, {a.channels} channel(s), mode {m}) "
              "in the MicroPython VM ...", flush=True)
        reps = run_firmware(a.scenario, m, cal, a.channels, a.seed)
        acks = [r for r in reps if not isinstance(r, Telemetry)]
        bad = [r for r in acks if not r.ok]
        if bad:
            raise SimError(f"the device refused: {bad[0].words()}")
        tel = [r for r in reps if isinstance(r, Telemetry)]
        stem = Path(a.scenario).stem
        path = out / f"{stem}-{m}.csv"
        write_csv(path, tel, {
            "firmware": __version__, "board": "sim", "scenario": a.scenario, "mode": m,
            "i0_ua": cal.i0_ua, "t0_us": cal.t0_us, "x_star_ohm": cal.x_star_ohm, "y_star_pc": cal.y_star_pc,
            "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
        })
        runs[m] = tel
        stops = {STOP_WORDS.get(t.stop, t.stop) for t in tel if t.stop not in (hp.STOP_NONE,)}
        print(f"  {len(tel)} pulses in {time.perf_counter() - t0:.1f} s -> {path}"
              + (f"; stops: {', '.join(sorted(map(str, stops)))}" if stops else ""))
    print()
    print("mQ error: |median(measured - target)| over each hold, in uC/kohm (the paper's settle threshold: 2.5e-05);")
    print("(bound) = the law needs I or T beyond its limits, which are held (paper, Discussion)")
    for line in phase_table(keys, duration, runs):
        print(line)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="steadytouch", description="Constant-sensation electrotactile stimulation: host tools.")
    p.add_argument("--version", action="version", version=f"steadytouch {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser(
        "sim", help="run the firmware in the MicroPython VM against a simulated electrode",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n  steadytouch sim peel\n  steadytouch sim gel --mode akhtar --out runs/\n"
               "  steadytouch sim my-disturbance.csv   (columns time_s,contact,hydration)",
    )
    s.add_argument("scenario", nargs="?", default="peel", help="steady, peel, gel, gel-step, exercise, off, or a .csv file")
    s.add_argument("--mode", choices=["akhtar", "open", "both"], default="both")
    s.add_argument("--channels", type=int, choices=[1, 2, 3, 4], default=1)
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--out", default="out", help="folder for the CSV files (default: out/)")
    s.add_argument("--i0-ua", type=int, default=1000)
    s.add_argument("--t0-us", type=int, default=1000)
    s.add_argument("--x-star-ohm", type=int, default=-1670)
    s.add_argument("--y-star-pc", type=int, default=186000)
    s.set_defaults(func=cmd_sim)
    return p


def main(argv=None) -> int:
    a = build_parser().parse_args(argv)
    try:
        return a.func(a)
    except SimError as e:
        print(f"steadytouch: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("steadytouch: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
