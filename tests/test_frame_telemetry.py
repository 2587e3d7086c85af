"""stim.Stimulator._encode_telemetry (viper: the fields stored straight into the
report buffer) writes the same 64 bytes as one struct.pack_into of
hid_protocol's telemetry layout (stim._TEL_FMT, the encoding it replaced), for
every field at both ends of its range and 300 random reports, in the MicroPython VM; it
allocates nothing (heap-locked) and advances the report sequence number."""

import json
import random

import hid_protocol as hp
import sensation_core as sc
from fw_harness import run_fw

RANGES = {  # field: (lowest, highest); u16 fields take the low 16 bits, so they go beyond 0xFFFF;
    # the counters (overruns, loop us) saturate (hid_protocol.sat16)
    "ch": (0, 1), "mode": (0, 5), "stop": (0, 7), "seq": (0, 2**30 - 1), "frame_t": (0, 2**30 - 1),
    "di": (0, 2**20), "dt": (0, 2**20), "vp": (-(2**30) + 1, 2**30 - 1), "rp": (-(2**30) + 1, 2**30 - 1),
    "me": (-(2**30) + 1, 2**30 - 1), "mqt": (-(2**30) + 1, 2**30 - 1),
    "mql": (-(2**29) + 1, 2**29 - 1),  # the measured mQ: within sensation_core's _MQ_CAP (a word + 2**29 holds it)
    "status": (0, 2**20), "ni": (0, 2**20), "nt": (0, 2**20), "over": (-3, 2**20), "loop": (-3, 2**20),
    "armed": (0, 1), "held": (0, 1), "keepalive_ms": (0, 5000), "cal": (0, 1), "rate": (10, 100),
    "ds": (0, 2**20), "mc": (0, 1),
}


def cases():
    """Every field at its lowest and highest (the others random), then random values (fixed seed)."""
    rnd = random.Random(12)
    out = []
    for name, (lo, hi) in list(RANGES.items()) * 2 + [(None, (0, 0))] * 300:
        v = {k: rnd.randint(a, b) for k, (a, b) in RANGES.items()}
        if name:
            v[name] = lo if len(out) < len(RANGES) else hi
        out.append(v)
    return out


def test_viper_telemetry_is_the_struct_layout_byte_for_byte(tmp_path):
    cases_ = cases()
    (tmp_path / "cases.json").write_text(json.dumps(cases_))
    _, res, _ = run_fw(f"""
        import struct, micropython
        with open({json.dumps(str(tmp_path / "cases.json"))}) as fh:
            cases = json.loads(fh.read())
        s, board, usb, clock = make("steady", n=2)
        got = []
        want = []
        for v in cases:
            c = s.chans[v["ch"]]
            ctl = c.ctl
            ctl.mode = v["mode"]; c.stop = v["stop"]; s.seq = v["seq"]; s.frame_t = v["frame_t"]
            c.di = v["di"]; c.dt = v["dt"]; c.vp = v["vp"]; c.rp = v["rp"]; ctl.me_ua2ms = v["me"]
            ctl.mq_target_fc_per_ohm = v["mqt"]; ctl.mq_last_fc_per_ohm = v["mql"]; ctl.status = v["status"]
            ctl.i_ua = v["ni"]; ctl.t_us = v["nt"]; s.overruns = v["over"]; s.loop_us = v["loop"]
            c.armed = bool(v["armed"]); c.held = bool(v["held"]); s.keepalive_ms = v["keepalive_ms"]
            c.cal_pulse = bool(v["cal"]); c.delivered_status = v["ds"]; c.mode_set = bool(v["mc"])
            mc = c.mode_set and c.di != 0  # (reported, then cleared, with a pulse only)
            s.rate_hz = v["rate"]
            for k in range(64):
                s.tel[c.ch][k] = 0
            micropython.heap_lock()
            s._encode_telemetry(c)  # allocates nothing (else MemoryError)
            micropython.heap_unlock()
            got.append(bytes(s.tel[c.ch]).hex())
            f = (hp.FLAG_ARMED if c.armed else 0) | (hp.FLAG_HELD if c.held else 0) | \\
                (hp.FLAG_KEEPALIVE if s.keepalive_ms else 0) | (hp.FLAG_CALIBRATING if c.cal_pulse else 0) | \\
                (hp.FLAG_MODE_SET if mc else 0)
            assert c.mode_set == bool(v["mc"] and not mc)
            ref = bytearray(64)
            struct.pack_into(stim._TEL_FMT, ref, 0, hp.REP_TELEMETRY, c.ch, ctl.mode, c.stop, v["seq"],
                             s.frame_t, c.di & 0xFFFF, c.dt & 0xFFFF, c.vp, c.rp, ctl.me_ua2ms,
                             ctl.mq_target_fc_per_ohm, ctl.mq_last_fc_per_ohm if c.di else 0, ctl.status & 0xFFFF,
                             ctl.i_ua & 0xFFFF, ctl.t_us & 0xFFFF, hp.sat16(s.overruns), hp.sat16(s.loop_us), f,
                             s.rate_hz, c.delivered_status & 0xFFFF)
            want.append(bytes(ref).hex())
            assert s.seq == (v["seq"] + 1) & 0x3FFFFFFF
        result(got=got, want=want)
    """)
    got, want = res[0]["got"], res[0]["want"]
    assert len(got) == len(cases_)
    bad = [k for k in range(len(cases_)) if got[k] != want[k]]
    assert not bad, f"case {cases_[bad[0]]}: {got[bad[0]]} != {want[bad[0]]}"


def test_every_reported_mq_is_measured_against_the_pulse_delivered():
    """The controller measures mQ on the pulse the board delivered (stim._control stores it on
    the controller before update; review of session 16: dropping those two stores passed every
    other test). On the realistic board the delivered current differs from the commanded one
    (DAC steps, gain), and a held raise differs from the controller's proposal: every report of a
    measured pulse must carry mQ = (I T - y*) 1000 / (Rp - x*), floored toward 0, of its own
    delivered I, T and Rp (sensation_core's Eq. 2 with muldiv), in every mode that measures it."""
    from steadytouch.protocol import Telemetry

    for mode in (sc.MODE_AKHTAR, sc.MODE_FAST):
        reports, _, _ = run_fw(f"""
            s, board, usb, clock = make("peel", ideal=False)
            start(s, i0=1000, t0=1000, x=-1670, y=186000, mode={mode})
            s.run(600)
            dump(usb)
        """)
        tel = [r for r in reports if isinstance(r, Telemetry)]
        checked = 0
        for t in tel:
            if not t.i_ua or t.flags & hp.FLAG_CALIBRATING or t.stop or t.status & sc.ST_FAULT_MASK:
                continue
            n = t.i_ua * t.t_us - 186000
            want = abs(n) * 1000 // (t.rp_ohm + 1670)
            assert t.mq_last_fc_per_ohm == (want if n >= 0 else -want), (mode, t)
            checked += 1
        assert checked >= 1000, (mode, checked)  # 2 channels x 600 frames, the calibration pulses and any latch aside
