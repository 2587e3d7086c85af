"""The firmware's real entry point on the emulated chip: `import main` runs
main_rp2() (board_rp2.Board with USB HID, stim.Stimulator, the endless loop) as
the board does at boot; the emulated host sends its commands as HID OUT reports
and reads the telemetry with host/protocol.py, and the gate's edges show the
pulses the telemetry reports."""

import pytest

import hid_protocol as hp
import sensation_core as sc
from steadytouch.protocol import Ack, Commands, Telemetry, decode

from .harness import ChipError


def test_main_runs_the_loop_driven_over_hid(chip, cfg):
    chip.wiring(cfg, cfg.N_CHANNELS)
    chip.load(0, rp_ohm=10000)
    chip.load(1, rs_ohm=470, rp_ohm=4700)
    cmd = Commands()
    sent = [cmd.set_mode(sc.MODE_AKHTAR), cmd.calibrate(1000, 1000, -1670, 186000), cmd.arm()]
    chip.hid(send=sent)  # handed over once the board's HID OUT endpoint is armed
    with pytest.raises(ChipError, match="timeout"):  # the loop never returns to the REPL
        chip.exec("import main", timeout_ms=1500)
    reps = [decode(bytes.fromhex(x)) for _t, x in chip.hid()["reports"]]
    acks = [r for r in reps if isinstance(r, Ack)]
    tel = [r for r in reps if isinstance(r, Telemetry)]
    assert [(a.command, a.result) for a in acks] == [(r[hp.O_OUT_CMD], hp.RES_OK) for r in sent]
    fired = [t for t in tel if t.i_ua]
    pulses = chip.take()["pulses"]
    assert len(fired) >= 2 * 20  # > 20 frames at 50 Hz in the second after start-up
    # every pulse the telemetry reports is a gate pulse, in order; the run is cut at a fixed emulated time,
    # which may fall inside a frame after its pulses and before or while their reports go out (a frame sends
    # its telemetry after all its pulses, channel by channel): the pulses with no report are exactly the last
    # ones, of that one frame: at most one a channel, consecutive channels in the frame's order — from ch0
    # (cut before the first report) or up to the last channel (cut between two reports) — all after the last
    # reported pulse, within one period
    assert len(fired) <= len(pulses), (len(fired), len(pulses))
    for t, p in zip(fired, pulses):
        assert (t.channel, t.t_us * 1000) == (p["ch"], p["fall_ns"] - p["rise_ns"])
        assert t.stop == hp.STOP_NONE
    rest = pulses[len(fired):]
    chs = [p["ch"] for p in rest]
    assert len(rest) <= cfg.N_CHANNELS and chs == list(range(chs[0], chs[0] + len(chs))) if rest else True, rest
    assert not rest or chs[0] == 0 or chs[-1] == cfg.N_CHANNELS - 1, rest
    last = pulses[len(fired) - 1]
    assert all(p["rise_ns"] > last["fall_ns"] for p in rest), (last, rest)
    assert not rest or rest[-1]["rise_ns"] - rest[0]["rise_ns"] < 1_000_000_000 // 50, rest
    # the frame that handled the three commands overran (each command costs ~6 ms on the
    # chip, docs/hardware.md); telemetry carries the previous frame's loop_us and the count.
    # No frame after it overruns.
    cal = [t for t in fired if t.flags & hp.FLAG_CALIBRATING]
    assert len(cal) == 4 and cal[-1] is fired[3]  # two calibration pulses a channel (two that agree: Rp0)
    assert {t.overruns for t in fired[2:]} == {fired[2].overruns} and fired[2].overruns <= 1
    assert all(t.loop_us < 20000 for t in fired[4:])
    last = {t.channel: t for t in fired}
    assert abs(last[0].rp_ohm - 10000) < 150 and abs(last[1].rp_ohm - 5170) < 100
