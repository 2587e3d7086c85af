"""Memory of the real firmware on the emulated chip (issue 12, deliverable 4): main.py's
set-up (board_rp2.Board with USB HID, stim.Stimulator, every module loaded), then its
main loop with both channels calibrated and armed over HID: after the first chunk of
frames (its warm-up), the loop allocates nothing and keeps nothing. The 10 000-frame
run and the figures: bench/chip_memory.py, docs/performance.md."""

import importlib.util

from .harness import ROOT


def _bench():
    spec = importlib.util.spec_from_file_location("chip_memory", ROOT / "bench" / "chip_memory.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_main_loop_keeps_and_allocates_nothing_per_frame(chip_host, cfg):
    r = _bench().run(frames=300, chunk=100, host=chip_host)
    assert r["frames"] == 300 and r["channels"] == cfg.N_CHANNELS
    assert r["reports"] >= 250 * cfg.N_CHANNELS  # the channels ran and the host read their telemetry
    assert r["allocated_after_first"] == 0  # chunks 2 and 3: not one byte allocated, GC off
    assert r["kept"] == 0  # heap in use after gc.collect() the same after every chunk
    assert r["free0"] > 0 and r["free0"] + r["alloc0"] > 200_000  # the rp2 port's ~240 KB heap, measured
