"""ADC + DMA capture on the emulated chip: the harness puts the electrode model's
monitor voltage on the ADC input at each conversion while the gate is high
(V = I (Rs + Rp (1 - e^(-t/tau))), firmware/sim_electrode.py's model, I from the
DAC code the board set), and the real Stimulator on the real Board reports the
model's Rp within the ADC's resolution."""

import math

import pytest

import sensation_core as sc

from .harness import make_board

RUN = """
s = stim.Stimulator(b, board_rp2.Clock(), cfg, {n}, 50)
buf = bytearray(hp.REPORT_LEN)
for rep in (hp.cmd_set_mode(buf, {mode}), hp.cmd_calibrate(bytearray(64), hp.CH_ALL, {i0}, {t0}, -1670, 186000),
            hp.cmd_arm(bytearray(64), hp.CH_ALL)):
    assert s.handle(rep, time.ticks_us()) == hp.RES_OK
s.sync_outputs()
rows = []
for f in range({frames}):
    s.run(1)
    for c in s.chans:
        rows.append((c.ch, c.di, c.dt, c.vp, c.rp, c.stop, list(b.adc[c.ch][:c.dt // cfg.ADC_SAMPLE_US + 2])))
print(rows)
"""


def model_ohm(load, t_us):
    rs, rp, tau = load
    return rs + (rp * (1 - math.exp(-t_us / tau)) if tau else rp)


@pytest.fixture(scope="module")
def board(chip_host, cfg):
    """One chip with the real Board for this module; each test starts from stop_all()."""
    chip = chip_host.boot(chip_host.image)
    make_board(chip, cfg)
    return chip


@pytest.fixture()
def chip(board):
    board.exec("b.stop_all()")
    board.take()
    return board


def run(chip, cfg, loads, i0, t0, frames=4, mode=sc.MODE_OPEN_LOOP):
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


@pytest.mark.parametrize("i0, t0", [(1000, 1000), (2000, 300), (500, 4000)])
def test_rp_of_resistors_matches_within_one_adc_count(chip, cfg, i0, t0):
    loads = [(0, 10000, 0), (470, 4700, 0)]  # a 10 kohm and a 5.17 kohm resistor
    rows, pulses, _ = run(chip, cfg, loads, i0, t0)
    assert len(rows) == 8 and len(pulses) == 8
    for (ch, di, dt, vp, rp, stop, _buf), p in zip(rows, pulses):
        assert (ch, dt, stop) == (p["ch"], t0, 0)
        assert (p["fall_ns"] - p["rise_ns"]) == t0 * 1000
        # the stimulator drives what the DAC code says (never more than asked, less by under one 2.44 uA
        # step), and the firmware takes that delivered current (rounded to 1 uA) as the truth
        assert p["i_ua"] == dac_ua(cfg, i0) and i0 - cfg.AMP_UA_AT_FULL / 4096 < p["i_ua"] <= i0
        assert di == int(p["i_ua"] + 0.5)  # half up, as dac_mcp4822.ua_for
        # Rp = Vp / I_delivered: within one ADC count of the load itself
        expect = model_ohm(loads[ch], t0)
        assert abs(rp - expect) <= count_ohm(cfg, i0) + 1, (ch, rp, expect)


@pytest.mark.parametrize("t0", [200, 1000, 4000])
def test_capture_of_an_electrode_is_sample_exact_and_rp_is_the_model_at_the_peak_sample(chip, cfg, t0):
    """An Rs + (Rp || C) electrode: Vp still rises at the end of the pulse. The DMA
    buffer holds exactly the conversions the ADC made, in order; Vp is their median-
    of-3 peak; Rp is the model at the time of that sample, within one count; that
    capture reaches the last ADC period of the pulse."""
    load = (500, 20000, 450)  # sim_electrode's defaults give tau = rho * C ~ 450 us on dry skin
    i0 = 1000
    rows, pulses, samples = run(chip, cfg, [load], i0, t0, frames=2)
    uv = cfg.VMON_UV_PER_COUNT
    dt_ns = cfg.ADC_SAMPLE_US * 1000
    for (ch, di, dt, vp, rp, stop, buf), p in zip(rows, pulses):
        n = len(buf)
        # the conversions started around this pulse, as the harness delivered them
        conv = [(t, v) for a, t, v in samples if p["rise_ns"] - 100_000 <= t <= p["fall_ns"] + 3 * dt_ns]
        first = next(k for k, (t, v) in enumerate(conv) if t >= p["rise_ns"] - n * dt_ns)
        got = conv[first:first + n]
        assert [v for _t, v in got] == buf, "the DMA buffer is not the ADC's conversions in order"
        assert all(b - a == dt_ns for (a, _), (b, _) in zip(got, got[1:])), "ADC not free-running at ADC_SAMPLE_US"
        med = [sorted(buf[k - 2:k + 1])[1] for k in range(2, n)]
        peak = max(med)
        assert vp == peak * uv // 1000
        k_peak = med.index(peak) + 1  # the middle sample of the window
        t_peak = got[k_peak][0]
        assert p["rise_ns"] < t_peak < p["fall_ns"]
        # the capture reaches the end of the pulse: its last conversion inside the pulse is within one period
        assert p["fall_ns"] - dt_ns <= max(t for t, _v in got if t < p["fall_ns"])
        expect = model_ohm(load, (t_peak - p["rise_ns"]) / 1000)  # Rp from the delivered current
        assert abs(rp - expect) <= count_ohm(cfg, i0) + 1, (rp, expect)
        # and how far that is below the model at the end of the pulse (reported, not a pass mark)
        print(f"T={t0} us: Rp {rp} ohm, model at the end {model_ohm(load, t0):.0f} ohm, "
              f"peak sample {(p['fall_ns'] - t_peak) / 1000:.1f} us before the fall")


def test_electrode_off_reads_compliance_and_latches_the_channel(chip, cfg):
    import hid_protocol as hp

    chip.host.call("load", ch=0, load={"open": True})
    rows = chip.eval_out(RUN.format(n=1, mode=sc.MODE_AKHTAR, i0=1000, t0=1000, frames=3))
    pulses = chip.take()["pulses"]
    assert rows[0][5] == hp.STOP_ELECTRODE_OFF and rows[0][3] >= cfg.COMPLIANCE_MV * cfg.ELECTRODE_OFF_PERMILLE // 1000
    assert len(pulses) == 1  # the one pulse that found it off; nothing after the latch
    assert [r[1] for r in rows[1:]] == [0, 0]
