"""ADC + DMA capture on the emulated chip: the harness puts the electrode model's
monitor voltage on the ADC input at each conversion while the gate is high
(V = I (Rs + Rp (1 - e^(-t/tau))), firmware/sim_electrode.py's model, I from the
DAC code the board set; 0 once the gate is low), and the real Stimulator on the
real Board reports the model's end-of-pulse Rp within the ADC's resolution.

The capture (board_rp2, issue 13): conversions every ADC_SAMPLE_US = 2 us from
the ADC's start, _CAPTURE_LEAD_US before the gate rises, DMA'd into a ring that
keeps the last ADC_WINDOW; the falling edge lies in that window and the last
conversion before it started within the last 2 us of the pulse, for every T.
The firmware's Vp (stim._peak_counts) reads the window: on a pulse the last sample
before the edge (0-2 us early), or where the guard caps it the one before (2-4 us)."""

import math

import pytest

import hid_protocol as hp
import sensation_core as sc
from test_frame_peak import packed, reference

US = 1000  # ns
RUN = """
s = stim.Stimulator(b, board_rp2.Clock(), cfg, {n}, 50)
buf = bytearray(hp.REPORT_LEN)
# wide soft limits: up to the current and charge the board holds (s.lim at boot: with no DAC gain
# applied the hard limits x 0.965, stim._fit_limits), the shortest width
for rep in (hp.cmd_set_limits(bytearray(64), 100, s.lim[1], hp.T_FLOOR_US, s.lim[3], s.lim[4]),
            hp.cmd_set_mode(buf, {mode}), hp.cmd_calibrate(bytearray(64), hp.CH_ALL, {i0}, {t0}, -1670, 0),
            hp.cmd_arm(bytearray(64), hp.CH_ALL)):
    assert s.handle(rep, time.ticks_us()) == hp.RES_OK
s.sync_outputs()
rows = []
for f in range({frames}):
    s.run(1)
    for c in s.chans:
        rows.append((c.ch, c.di, c.dt, c.vp, c.rp, c.stop, c.n_samples, list(b.adc[c.ch])))
print(rows)
"""
# accepted widths: the shortest, odd ones and ones not a multiple of the sample period, to >= 2000 us
WIDTHS = [hp.T_FLOOR_US, hp.T_FLOOR_US + 1, 33, 99, 100, 101, 333, 1000, 2001]


def model_ohm(load, t_us):
    rs, rp, tau = load
    return rs + (rp * (1 - math.exp(-t_us / tau)) if tau else rp)


def run(chip, loads, i0, t0, frames=2, mode=sc.MODE_OPEN_LOOP):
    for k, (rs, rp, tau) in enumerate(loads):
        chip.load(k, rs_ohm=rs, rp_ohm=rp, tau_us=tau)
    rows = chip.eval_out(RUN.format(n=len(loads), mode=mode, i0=i0, t0=t0, frames=frames))
    r = chip.take()
    return rows, r["pulses"], r["samples"]


def count_ohm(cfg, i_ua):
    """One ADC count, in ohm of Rp, at current i_ua."""
    return cfg.VMON_UV_PER_COUNT / i_ua


def dac_ua(cfg, i_ua):
    """The current the DAC delivers for i_ua: the largest 12-bit code not above it, times the LSB."""
    return (i_ua * 4096 // cfg.AMP_UA_AT_FULL) * cfg.AMP_UA_AT_FULL / 4096


def peak_counts(v, cfg):
    """Vp as stim._measure reads the capture's last samples v: _peak_counts (its reference, checked against the
    viper code there) on those up to 20 us past the fall (stim._C_PEAK_POST_US), at most 32 of them."""
    hi = len(v) - (cfg.ADC_POST_US - 20) // cfg.ADC_SAMPLE_US
    return reference(v, max(0, hi - 32), hi)


def capture(cfg, samples, p, adc_input):
    """The ADC's run of conversions around pulse p, as the host delivered them: [(ns, counts)]
    from the conversion the capture started with, 2 us apart."""
    conv = [(t, v) for a, t, v in samples if a == adc_input and p["rise_ns"] - 200 * US <= t <= p["fall_ns"] + 200 * US]
    k = max(j for j, (t, _v) in enumerate(conv) if t <= p["rise_ns"])
    while k > 0 and conv[k][0] - conv[k - 1][0] == cfg.ADC_SAMPLE_US * US:
        k -= 1  # back to the start of this run of conversions
    return conv[k:]


@pytest.mark.parametrize("t0", WIDTHS)
def test_the_capture_window_holds_the_falling_edge_and_a_sample_from_the_last_2_us(on_board, cfg, t0):
    """Emulated-us facts of the capture, on both channels: the window is the capture's
    last n conversions in order, 2 us apart, starting 12.0-14.2 us before the rise;
    the falling edge is in it with samples on both sides, and the last conversion before
    the edge started within its last 2 us; the firmware's Vp is _peak_counts of the window."""
    rows, pulses, samples = run(on_board, [(0, 10000, 0), (470, 4700, 0)], 1000, t0)
    assert len(rows) == len(pulses) == 4
    leads = []
    for (ch, di, dt, vp, rp, stop, n, buf), p in zip(rows, pulses):
        assert (ch, dt, stop) == (p["ch"], t0, 0) and p["fall_ns"] - p["rise_ns"] == t0 * US
        conv = capture(cfg, samples, p, cfg.ADC_INPUTS[ch])
        total = (t0 + 12 + cfg.ADC_POST_US) // cfg.ADC_SAMPLE_US  # board_rp2: _CAPTURE_LEAD_US + _CAPTURE_POST_US
        assert n == min(total, cfg.ADC_WINDOW) and len(buf) == cfg.ADC_WINDOW
        got = conv[total - n:total]
        assert [v for _t, v in got] == buf[cfg.ADC_WINDOW - n:], "the window is not the capture's last conversions"
        assert all(b - a == cfg.ADC_SAMPLE_US * US for (a, _), (b, _) in zip(got, got[1:]))
        leads.append((p["rise_ns"] - conv[0][0]) / US)
        before = [t for t, _v in got if t < p["fall_ns"]]
        after = [t for t, _v in got if t >= p["fall_ns"]]
        assert len(after) >= 5 and len(before) >= 2, (len(before), len(after))
        assert p["fall_ns"] - before[-1] <= cfg.ADC_SAMPLE_US * US  # the pulse's last 2 us
        assert vp == peak_counts(buf[cfg.ADC_WINDOW - n:], cfg) * cfg.VMON_UV_PER_COUNT // 1000
    print(f"T={t0} us: lead {min(leads):.3f}-{max(leads):.3f} us")
    assert all(12.0 <= x <= 16.0 for x in leads), leads  # board_rp2._CAPTURE_LEAD_US = 12


@pytest.mark.parametrize("i0, t0", [(1000, hp.T_FLOOR_US), (1000, 1000), (2000, 301), (500, 4000)])
def test_rp_of_resistors_matches_within_one_adc_count(on_board, cfg, i0, t0):
    loads = [(0, 10000, 0), (470, 4700, 0)]  # a 10 kohm and a 5.17 kohm resistor
    rows, pulses, _ = run(on_board, loads, i0, t0, frames=3)
    assert len(rows) == 6 and len(pulses) == 6
    for (ch, di, dt, vp, rp, stop, _n, _buf), p in zip(rows, pulses):
        assert (ch, dt, stop) == (p["ch"], t0, 0)
        assert (p["fall_ns"] - p["rise_ns"]) == t0 * US
        # the stimulator drives what the DAC code says (never more than asked, less by under one 2.44 uA
        # step), and the firmware takes that delivered current (rounded to 1 uA) as the truth
        assert p["i_ua"] == dac_ua(cfg, i0) and i0 - cfg.AMP_UA_AT_FULL / 4096 < p["i_ua"] <= i0
        assert di == math.ceil(p["i_ua"])  # rounded up, as dac_mcp4822.ua_for
        # Rp = Vp / I_delivered: within one ADC count of the load itself
        expect = model_ohm(loads[ch], t0)
        assert abs(rp - expect) <= count_ohm(cfg, i0) + 1, (ch, rp, expect)


# Rs + (Rp || C) electrodes across sim_electrode's range (tau = rho c: ~50 us on wet gel to ~900 us
# on dry skin), and a 10 kohm resistor, read at 1 mA
ELECTRODES = [(300, 3000, 50), (500, 20000, 450), (1500, 40000, 900)]


@pytest.mark.parametrize("t0", WIDTHS)
def test_rp_is_the_model_at_the_end_of_the_pulse_within_the_adc_resolution(on_board, cfg, t0):
    """The Rp the firmware reports against the harness model's end-of-pulse Rp, for T from the
    shortest accepted to 2001 us: within one ADC count, plus the model's rise over the
    estimator's 2-4 us before the edge (the ADC's time resolution; it is 1 count or less
    wherever the model rises by less than a count in 4 us). Exactly: Rp is the model at the
    time of the sample the estimator read, within one count. Figures printed."""
    i0 = 1000
    for load in ELECTRODES:
        rows, pulses, samples = run(on_board, [load], i0, t0)
        res = count_ohm(cfg, i0)
        for (ch, di, dt, vp, rp, stop, n, buf), p in zip(rows, pulses):
            assert stop == 0 and dt == t0
            end = model_ohm(load, t0)
            rise4 = end - model_ohm(load, t0 - 2 * cfg.ADC_SAMPLE_US)
            assert end - rise4 - res - 1 <= rp <= end + res + 1, (load, t0, rp, end, rise4)
            if rise4 < res:
                assert abs(rp - end) <= 2 * res + 1
            # the sample read: the latest one inside the pulse holding the value read
            conv = capture(cfg, samples, p, cfg.ADC_INPUTS[ch])
            total = (t0 + 12 + cfg.ADC_POST_US) // cfg.ADC_SAMPLE_US
            got = conv[total - n:total]
            v = peak_counts(buf[cfg.ADC_WINDOW - n:], cfg)
            t_read = max((t - p["rise_ns"]) / US for t, x in got if x == v and t < p["fall_ns"])
            assert 0 <= t_read < t0 and t0 - t_read <= 2 * cfg.ADC_SAMPLE_US
            assert abs(rp - model_ohm(load, t_read)) <= res + 1 + rp / 1000  # (+ di rounded to 1 uA)
            print(f"T={t0} us, load {load}: Rp {rp} ohm, model at the end {end:.0f} ohm "
                  f"({(rp - end) / end:+.2%}), read {t0 - t_read:.2f} us before the fall")


def test_electrode_off_reads_compliance_and_latches_the_channel(on_board, cfg):
    on_board.host.call("load", ch=0, load={"open": True})
    rows = on_board.eval_out(RUN.format(n=1, mode=sc.MODE_AKHTAR, i0=1000, t0=1000, frames=3))
    pulses = on_board.take()["pulses"]
    assert rows[0][5] == hp.STOP_ELECTRODE_OFF and rows[0][3] >= cfg.COMPLIANCE_MV * cfg.ELECTRODE_OFF_PERMILLE // 1000
    assert len(pulses) == 1  # the one pulse that found it off; nothing after the latch
    assert [r[1] for r in rows[1:]] == [0, 0]


def test_the_estimator_compiled_for_the_chip_is_the_reference(on_board):
    """stim._peak_counts as mpy-cross -march=armv6m built it, on the chip: the reference on 300
    windows (pulses with a spike or a dropout, random ones, rails), under the heap lock."""
    import random

    rnd = random.Random(5)
    cases = []
    for j in range(300):
        n = rnd.randint(1, 32)
        if j % 3 == 0:
            v = [rnd.choice([0, 1, 4094, 4095]) for _ in range(32)]
        else:
            pre = rnd.randint(1, n)
            step = rnd.randint(0, 40)
            base = rnd.randint(0, 3000)
            v = [rnd.randint(0, 4095) for _ in range(32 - n)]
            v += [min(4095, base + k * step + rnd.randint(0, 6)) for k in range(pre)]
            v += [max(0, v[-1] - rnd.randint(1, 900) - 3 * k) for k in range(n - pre)]
            v[rnd.randint(32 - n, 31)] = rnd.choice([0, 4095, rnd.randint(0, 4095)])
        cases.append((v, 32 - n))
    out = []
    for c in range(0, len(cases), 25):  # a few at a time: compiling a long literal starves the watchdog
        out += on_board.eval_out(f"""
from array import array
cases = {cases[c:c + 25]}
bufs = [array('H', v) for v, lo in cases]
got = [0] * len(cases)
def read_all(bufs, cases, got):
    micropython.heap_lock()
    try:
        for k in range(len(cases)):
            got[k] = stim._peak_counts(bufs[k], cases[k][1], 32)
    finally:
        micropython.heap_unlock()
read_all(bufs, cases, got)
print(got)""")
    assert out == [packed(v, lo, 32) for v, lo in cases]


@pytest.mark.parametrize("t0", [1000, 2001])
def test_tau_is_read_from_the_decay_after_the_fall_on_the_chip(on_board, cfg, t0):
    """The harness feeds the ADC the skin's discharge after the fall, V(fall) e^(-t/tau) (host/emu/host.mjs),
    for the ADC_POST_US the capture runs past it; the firmware's tau (stim._measure: decay.ltau_q16 as
    mpy-cross built it, on the samples after the edge _peak_counts found) is each load's within 3 %
    (the counts' rounding: 1 / (amplitude x the windows' span), tests/test_decay.py); a resistor has no
    decay to read: 0."""
    script = RUN.replace("c.n_samples, list(b.adc[c.ch])", "c.ltau")
    for loads in (ELECTRODES[:2], [ELECTRODES[2], (10000, 0, 0)]):
        for k, (rs, rp, tau) in enumerate(loads):
            on_board.load(k, rs_ohm=rs, rp_ohm=rp, tau_us=tau)
        rows = on_board.eval_out(script.format(n=2, mode=sc.MODE_OPEN_LOOP, i0=1000, t0=t0, frames=2))
        on_board.take()
        assert len(rows) == 4
        for ch, di, dt, vp, rp, stop, ltau in rows:
            assert stop == 0 and di > 0 and dt == t0
            tau = loads[ch][2]
            if tau:
                got = 2 ** (ltau / 65536)
                print(f"T={t0} us, load {loads[ch]}: tau {got:.1f} us ({got / tau - 1:+.2%})")
                assert abs(got / tau - 1) < 0.03, (loads[ch], got)
            else:
                assert ltau == 0
