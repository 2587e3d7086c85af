"""The core's worst update on the emulated chip (issue 12, deliverable 3): MODE_FAST with
the skin model fitted by host/skin.py, replaying the closed loops of bench/controllers.py
with the most model work (bench/core_chip.py: the Rp each pulse read in CPython fed to the
chip's Controller.update). Emulated microseconds are deterministic: every update of the
replay takes at most 1700 us (issue 12 asks for 2000; measured 1423 worst over
bench/core_chip.py's cases after MODE_FAST was made viper, 1364 after session 15's searches),
and the chip's pulses are CPython's."""

import importlib.util
import struct
import sys

from .harness import ROOT

# the heaviest jumps of bench/core_chip.py's cases, their first UPDATES updates: a jump on most
# pulses under 0.3 % Rp noise, peel (74 of FAST_MODEL_WORK_MAX's 80 units; 76 at updates 132, 179,
# 180 until rule 4 refitted only on a move of 1/8 octave, session 29) and the step of +50 kohm at
# 700 uA (78 at updates 51-52, then Rp passes RP_MAX and the core stops: 53 updates; the +20 kohm
# step it replaces spends 74 since); since the search of the duration ceiling starts where the mE
# curve meets t_max (session 15) no closed loop of the benchmark runs out of the budget
CASES = (("peel", 0.003), ("step +50 700", 0.003))
UPDATES = 200
WORST_US = 1700


def _bench():
    spec = importlib.util.spec_from_file_location("core_chip", ROOT / "bench" / "core_chip.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_worst_update_with_the_skin_model_within_1_7_ms(chip, tmp_path):
    bench = _bench()
    saved = list(sys.path)
    try:
        want = bench.closed_loops(tmp_path, CASES, UPDATES)
    finally:
        sys.path[:] = saved
    for k in range(len(CASES)):
        chip.put((tmp_path / f"cl_{k}.bin").read_bytes(), f"/cl_{k}.bin")
    out = chip.exec(bench.CLOSED.replace("PAD", "0"), timeout_ms=300000)
    rows = [ln.split() for ln in out.splitlines() if ln.startswith("CASE")]
    assert len(rows) == len(CASES), out
    worst = {}
    for k, (row, (label, h)) in enumerate(zip(rows, want)):
        _, _k, n, _med, _p99, w, hc, jumps, _cuts = row
        recorded = struct.unpack("<14i", (tmp_path / f"cl_{k}.bin").read_bytes()[:56])[13]
        assert int(n) == recorded and recorded >= 50, (label, n, recorded)  # (UPDATES, or up to the core's stop)
        assert int(hc) == h, (label, "the chip's pulses differ from CPython's")
        assert int(jumps) >= 1, (label, "the replay made no model jumps: it tests nothing")
        worst[label] = int(w)
    assert max(worst.values()) <= WORST_US, worst
    assert min(worst.values()) >= 900, worst  # each replay does reach the model's heavy jumps
    # and a jump within a search's set-up of the whole FAST_MODEL_WORK_MAX (counted in CPython,
    # whose pulses the chip's are: the hash above)
    import sensation_core as sc
    import skin_model as sm

    most = 0
    for k in range(len(CASES)):
        b = (tmp_path / f"cl_{k}.bin").read_bytes()
        v = struct.unpack("<14i", b[:56])
        c = sc.Controller(*v[:5])
        c.calibrate(*v[5:10])
        c.set_mode(sc.MODE_FAST)
        c.set_skin(*v[10:13])
        for rp in struct.unpack(f"<{v[13]}i", b[56:56 + 4 * v[13]]):
            c.update(rp)
            most = max(most, c.skin.v[sm._V_WORK])
    assert most >= sm.FAST_MODEL_WORK_MAX - sm._ROOT_WORK, most
