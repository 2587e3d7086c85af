"""Memory of the real firmware on the emulated Pico (issue 12, deliverable 4).

Run: .venv/bin/python bench/chip_memory.py [--frames 10000] [--chunk 1000] [--channels N]

Boots MicroPython v1.28.0 for the Pico in rp2040js (host/emu: ../shared/emulator
beside the checkout, the device files compiled for armv6m in the board's /lib),
imports main.py without letting it start (a stand-in `sys` whose platform is not
"rp2" while it is imported), and does main_rp2()'s set-up: board_rp2.Board with USB
HID, stim.Stimulator, the Ctrl-C watch. Then:

- free heap after the set-up: gc.collect(), gc.mem_free() / gc.mem_alloc();
- the main loop itself (main.run_until_ctrl_c's body: s.run(1) while no Ctrl-C
  waits), every channel calibrated (MODE_AKHTAR) and armed over HID OUT reports,
  the emulated host reading the telemetry, in chunks of --chunk frames (one REPL
  call each, a progress line each): with the GC disabled during the chunk, the
  bytes allocated in it; after gc.collect(), the bytes kept since the first chunk.

Figures are the board's own gc counters (exact, deterministic in the emulator).
10 000 frames at 50 Hz are 200 s of emulated time: several minutes of wall time.
"""

import argparse
import ast
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT / "shared"), str(ROOT)]

import sensation_core as sc  # noqa: E402
from steadytouch.emu import ChipUnavailable, NoEmulator, load_cfg, mpy_cross, start_host  # noqa: E402
from steadytouch.protocol import Commands, Telemetry, decode  # noqa: E402

# main.py without its start: `import sys` in main finds this stand-in (sys.modules is
# looked up before the built-in modules), so `if sys.platform == "rp2": main_rp2()`
# is false while it is imported; main.sys is the real one afterwards.
IMPORT_MAIN = """
import sys, gc, machine, micropython
class _Sys:
    platform = 'bench'
    stdin = sys.stdin
sys.modules['sys'] = _Sys
try:
    import main
finally:
    del sys.modules['sys']
main.sys = sys
"""

# main_rp2()'s set-up, line for line (firmware/main.py), then the free heap
SETUP = """
import board_rp2, stim, time
board_rp2.watchdog_pause()
board = board_rp2.Board(main.cfg)
s = stim.Stimulator(board, board_rp2.Clock(), main.cfg)
stim.RUNNING = s
ctrl_c = main.CtrlC()
while board.usb is not None and not board.usb.is_open():  # (the emulated host enumerates it again)
    board_rp2.watchdog_pause()
    time.sleep_ms(5)
board_rp2.watchdog_pause()
gc.collect()
print(repr((gc.mem_free(), gc.mem_alloc())))
"""

# one chunk of the main loop (run_until_ctrl_c's body with a frame count); the watchdog
# runs during the chunk and is paused while the REPL waits for the next one
CHUNK = """
def chunk(n):
    gc.collect()
    gc.disable()
    board.feed_watchdog()
    machine.mem32[0x40058000] = machine.mem32[0x40058000] | 0x40000000
    micropython.kbd_intr(-1)
    k = 0
    a0 = gc.mem_alloc()
    while k < n and not ctrl_c.pressed():
        s.run(1)
        k += 1
    a1 = gc.mem_alloc()
    micropython.kbd_intr(3)
    board_rp2.watchdog_pause()
    gc.enable()
    gc.collect()
    return (k, a1 - a0, gc.mem_alloc(), gc.mem_free(), s.overruns)
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10000, help="frames of the main loop (default 10000)")
    ap.add_argument("--chunk", type=int, default=1000, help="frames per REPL call and progress line (default 1000)")
    ap.add_argument("--channels", type=int, default=0, help="channels (default: board_config's N_CHANNELS)")
    a = ap.parse_args()
    if a.frames < 1 or a.chunk < 1:
        sys.exit("chip_memory.py: --frames and --chunk must be >= 1")
    r = run(a.frames, a.chunk, a.channels, progress=True)
    print(f"free heap after main's set-up: {r['free0']} B free, {r['alloc0']} B used "
          f"(of {r['free0'] + r['alloc0']} B)")
    print(f"main loop, {r['frames']} frames x {r['channels']} channels: allocated with the GC off "
          f"{r['allocated']} B in all; kept after gc.collect() since the first chunk: {r['kept']} B "
          f"(first chunk, warm-up included: {r['kept_first']} B); telemetry reports read {r['reports']}, "
          f"overruns {r['overruns']}")


def run(frames, chunk, channels=0, progress=False, host=None):
    """The figures as a dict (this bench, and tests/chip/test_chip_memory.py with its host)."""
    cfg = load_cfg()
    n = channels or cfg.N_CHANNELS
    own = host is None
    if own:
        try:
            host = start_host(mpy_cross())
        except NoEmulator as e:
            sys.exit(str(e))
        except ChipUnavailable as e:
            sys.exit(f"chip_memory.py: {e}")
    try:
        chip = host.boot(host.image)
        chip.wiring(cfg, n)
        for ch in range(n):
            chip.load(ch, rs_ohm=470, rp_ohm=4700 + 2000 * ch)
        chip.exec(IMPORT_MAIN)
        if n != cfg.N_CHANNELS:
            chip.exec(f"main.cfg.N_CHANNELS = {n}")
        free0, alloc0 = chip.eval_out(SETUP)
        chip.exec(CHUNK)
        cmd = Commands()
        sent = [cmd.set_mode(sc.MODE_AKHTAR), cmd.calibrate(1000, 1000, -1670, 186000), cmd.arm()]
        chip.hid(send=sent)
        done = allocated = reports = 0
        kept_first = base = None
        t0 = time.monotonic()
        overruns = 0
        while done < frames:
            out = chip.exec(f"print(repr(chunk({min(chunk, frames - done)})))", timeout_ms=chunk * 100)
            k, alloc, used, free, overruns = ast.literal_eval(out.strip().splitlines()[-1])
            done += k
            allocated += alloc
            reps = [decode(bytes.fromhex(x)) for _t, x in chip.hid()["reports"]]
            reports += sum(isinstance(x, Telemetry) for x in reps)
            if base is None:
                base = used
                kept_first = used - alloc0
                first_alloc = alloc
            if progress:
                print(f"  frames {done}/{frames}: allocated {alloc} B in this chunk, heap used {used} B "
                      f"(kept since chunk 1: {used - base} B), free {free} B, overruns {overruns}, "
                      f"{time.monotonic() - t0:.0f} s wall", flush=True)
            if k == 0:
                break
        return {"free0": free0, "alloc0": alloc0, "frames": done, "channels": n, "allocated": allocated,
                "allocated_after_first": allocated - first_alloc,
                "kept": used - base, "kept_first": kept_first, "reports": reports, "overruns": overruns}
    finally:
        if own:
            host.close()


if __name__ == "__main__":
    main()
