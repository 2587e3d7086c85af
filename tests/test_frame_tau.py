"""The monitor's decay after the fall, read by the frame (stim._measure: decay.ltau_q16 on the capture's
samples after the falling edge _peak_counts found): log2 tau in Q.16 in every channel's telemetry
(ltau_q16), against the simulated electrode's own tau = R_skin Cp, on the ideal and the realistic board,
through a gel step (tau moves with hydration), in the MicroPython VM with every frame heap-locked."""

import statistics

import hid_protocol as hp
import sensation_core as sc
from steadytouch.protocol import Telemetry

from fw_harness import run_fw


def _runs():
    reports, res, _ = run_fw("""
        for ideal in (True, False):
            s, board, usb, clock = make("gel-step", n=1, ideal=ideal)
            start(s, mode=sc.MODE_FAST)
            out = []
            for k in range(200):
                s.run(1)
                c = s.chans[0]
                out.append((c.di, c.ltau, board.electrodes[0].tau, c.stop))
            dump(usb)
            result(out=out)
    """)
    tel = [t for t in reports if isinstance(t, Telemetry)]
    assert len(tel) == 400
    return [(tel[200 * k:200 * (k + 1)], res[k]["out"]) for k in (0, 1)]


def test_tau_read_after_every_pulse_follows_the_electrode():
    (ideal_tel, ideal), (real_tel, real) = _runs()
    for tel, out in ((ideal_tel, ideal), (real_tel, real)):
        assert all(stop == hp.STOP_NONE for *_, stop in out)  # no frame allocated (heap-locked: STOP_INTERNAL)
        assert [t.ltau_q16 for t in tel] == [lt for _, lt, _, _ in out]  # telemetry carries the frame's value
        assert all(t.ltau_q16 > 0 for t in tel if t.i_ua)
    taus = [tau for _, _, tau, _ in ideal]
    assert max(taus) > 1.3 * min(taus)  # the gel moved tau: the read follows it, not a constant
    ratio = [2 ** (lt / 65536) / tau for di, lt, tau, _ in ideal if di]
    assert len(ratio) == 200 and max(abs(r - 1) for r in ratio) < 0.02, (min(ratio), max(ratio))
    # the realistic board (ADC noise at 8.7 ENOB, E11 codes, the monitor's offset not yet corrected: tau
    # reads the decay to the offset): within 3 % at the median, 12 % at worst (measured 1.6 %, -5 / +10 %)
    ratio = [2 ** (lt / 65536) / tau for di, lt, tau, _ in real if di]
    assert len(ratio) == 200
    assert abs(statistics.median(ratio) - 1) < 0.03 and max(abs(r - 1) for r in ratio) < 0.12, (
        statistics.median(ratio), min(ratio), max(ratio))


def test_no_pulse_reads_no_tau():
    reports, _, _ = run_fw("""
        s, board, usb, clock = make("steady", n=1)
        start(s, mode=sc.MODE_AKHTAR)
        s.run(5)
        b = bytearray(64)
        assert apply(s, hp.cmd_disarm(b, hp.CH_ALL)) == 0
        s.run(3)
        dump(usb)
    """)
    tel = [t for t in reports if isinstance(t, Telemetry)]
    assert [t.ltau_q16 > 0 for t in tel] == [True] * 5 + [False] * 3
    assert sc.MODE_AKHTAR == tel[0].mode
