"""Configurations whose worst-case frame cannot fit its period are refused
(hid_protocol.frame_fits: rate x frame_us(channels, t_max) <= 1 s, the frame's
pulses overlapping the work of the channel before; docs/performance.md)."""

import hid_protocol as hp
from fw_harness import run_fw


def test_rule_numbers():
    # n pulses, a gap before each, pulses shorter than a channel's work stretched to it, then the tail
    assert hp.frame_us(1, 8000) == 300 + 8000 + 2200
    assert hp.frame_us(4, 2000) == 4 * 300 + 4 * 2000 + 2200
    assert hp.frame_us(4, 200) == 4 * 300 + 200 + 3 * 1800 + 2200
    assert hp.frame_fits(50, 4, 4150) and not hp.frame_fits(50, 4, 4151)
    assert hp.frame_fits(100, 2, 3600) and not hp.frame_fits(100, 2, 3601)
    assert hp.frame_fits(50, 2, 8000) and hp.frame_fits(50, 2, 8600) and not hp.frame_fits(50, 2, 8601)
    assert hp.t_max_fitting(50, 4) == 4150 and hp.t_max_fitting(100, 1) == 7500
    assert hp.t_max_fitting(100, 3) == 2300 and hp.t_max_fitting(100, 4) == 1200  # 4: stretched pulses, 1200 + 3 x 1800
    assert hp.rate_max_fitting(4, 8000) == 28


def test_t_max_fitting_is_the_largest_that_fits():
    for m in (0, 1):
        for n in (1, 2, 3, 4):
            for rate in range(hp.RATE_MIN_HZ, hp.RATE_MAX_HZ + 1):
                t = hp.t_max_fitting(rate, n, m)
                if t >= hp.T_FLOOR_US:
                    assert hp.frame_fits(rate, n, t, m) and not hp.frame_fits(rate, n, t + 1, m), (n, rate, t)
                    r = hp.rate_max_fitting(n, t, m)
                    assert rate <= r and not hp.frame_fits(r + 1, n, t, m)
                else:
                    assert not hp.frame_fits(rate, n, hp.T_FLOOR_US, m), (n, rate)


def test_device_refuses_a_frame_that_cannot_fit():
    _, res, _ = run_fw("""
        s, board, usb, clock = make("steady", n=2)
        b = bytearray(64)
        r = {"boot_t_max": s.lim[3]}
        r["rate100"] = apply(s, hp.cmd_set_mode(b, sc.MODE_AKHTAR, 100))
        r["detail100"] = s.tx[hp.O_DETAIL]
        r["rate_after"] = s.rate_hz
        r["lim4001"] = apply(s, hp.cmd_set_limits(b, 500, 10000, 100, 4001, 10000000))
        r["lim3600"] = apply(s, hp.cmd_set_limits(b, 500, 10000, 100, 3600, 10000000))
        r["rate100b"] = apply(s, hp.cmd_set_mode(b, sc.MODE_AKHTAR, 100))
        r["lim3601"] = apply(s, hp.cmd_set_limits(b, 500, 10000, 100, 3601, 10000000))
        r["detail3601"] = s.tx[hp.O_DETAIL]
        s4, _, _, _ = make("steady", n=4)
        r["boot4_t_max"] = s4.lim[3]
        r["boot4_100_t_max"] = make("steady", n=4, rate=100)[0].lim[3]
        result(**r)
    """)
    r = res[0]
    assert r["boot_t_max"] == 8000  # 2 channels at 50 Hz: 2 x (300 + 8000) + 2200 us = 18.8 ms
    assert r["rate100"] == hp.RES_OUT_OF_RANGE and r["detail100"] == hp.O_ARG + 1 and r["rate_after"] == 50
    assert r["lim4001"] == hp.RES_OK  # at 50 Hz it fits
    assert r["lim3600"] == hp.RES_OK and r["rate100b"] == hp.RES_OK
    assert r["lim3601"] == hp.RES_OUT_OF_RANGE and r["detail3601"] == hp.O_ARG + 6  # at 100 Hz it does not
    # 4 channels at 50 Hz: the default t_max lowered to fit, with room for a skin model's work
    assert r["boot4_t_max"] == 3950 == hp.t_max_fitting(50, 4, 1)
    assert r["boot4_100_t_max"] == 1200  # no model fits 4 channels at 100 Hz: the rule without one


def test_rule_with_a_skin_model():
    # a channel's work and the tail are longer with a model: FRAME_WORK_MODEL_US, FRAME_TAIL_MODEL_US
    assert hp.frame_us(2, 3200, 1) == 2 * 300 + 2 * 3200 + 3000
    assert hp.frame_us(4, 200, 1) == 4 * 300 + 200 + 3 * 3000 + 3000
    assert hp.t_max_fitting(100, 2, 1) == 3200 and hp.t_max_fitting(50, 4, 1) == 3950
    assert hp.t_max_fitting(100, 4, 1) < hp.T_FLOOR_US  # no skin model at 4 channels x 100 Hz
    for n in (1, 2, 3, 4):
        for rate in (10, 50, 77, 100):
            assert hp.t_max_fitting(rate, n, 1) <= hp.t_max_fitting(rate, n)


def test_device_refuses_a_skin_model_whose_work_cannot_fit():
    """SET_SKIN is refused (RES_NO_FRAME_TIME, nothing changed) where the model's
    work would not fit the frame; with a model set, SET_LIMITS and SET_MODE count it."""
    _, res, _ = run_fw("""
        b = bytearray(64)
        r = {}
        s, board, usb, clock = make("steady", n=4, rate=100)
        r["skin4_100"] = apply(s, hp.cmd_set_skin(b, hp.CH_ALL, 500, 36045, 14000))
        r["detail"] = s.tx[hp.O_DETAIL]
        r["model_after"] = [c.ctl.skin_rs_ohm for c in s.chans]
        s, board, usb, clock = make("steady", n=4)
        r["skin4_50"] = apply(s, hp.cmd_set_skin(b, 1, 500, 36045, 14000))
        r["lim4150_model"] = apply(s, hp.cmd_set_limits(b, 500, 10000, 100, 4150, 10000000))
        r["lim3950_model"] = apply(s, hp.cmd_set_limits(b, 500, 10000, 100, 3950, 10000000))
        r["unskin"] = apply(s, hp.cmd_set_skin(b, hp.CH_ALL, 0, 0, 0))
        r["lim4150"] = apply(s, hp.cmd_set_limits(b, 500, 10000, 100, 4150, 10000000))
        r["skin_at_4150"] = apply(s, hp.cmd_set_skin(b, 0, 500, 36045, 14000))
        result(**r)
    """)
    r = res[0]
    assert r["skin4_100"] == hp.RES_NO_FRAME_TIME and r["model_after"] == [0, 0, 0, 0]
    assert r["skin4_50"] == hp.RES_OK
    assert r["lim4150_model"] == hp.RES_OUT_OF_RANGE and r["lim3950_model"] == hp.RES_OK
    assert r["unskin"] == hp.RES_OK and r["lim4150"] == hp.RES_OK
    assert r["skin_at_4150"] == hp.RES_NO_FRAME_TIME


def test_host_refuses_a_skin_model_whose_work_cannot_fit():
    import pytest

    from steadytouch.protocol import CommandError, Commands

    with pytest.raises(CommandError, match=r"skin model's work does not fit the frame with 4 channels at 100 Hz"):
        Commands(frame=(4, 100, 1200)).set_skin(500, 36045, 14000)
    c = Commands(frame=(4, 50, 3950))
    c.applied(c.set_skin(500, 36045, 14000, 1))
    with pytest.raises(CommandError, match=r"t_max_us=4150 does not fit .* with a skin model set: at most 3950 us"):
        c.set_limits(500, 10000, 100, 4150, 10000000)
    c.applied(c.set_skin(0, 0, 0))  # removed on every channel
    c.set_limits(500, 10000, 100, 4150, 10000000)


def test_host_refuses_a_rate_or_t_max_whose_frame_cannot_fit():
    """host/protocol.Commands applies the device's rule once it knows the frame
    (from GET_INFO, then every acknowledged SET_MODE/SET_LIMITS): one clear
    CommandError naming the largest value that fits, no report built."""
    import pytest

    from steadytouch.protocol import CommandError, Commands

    c = Commands()
    c.set_mode(sc_mode(), 100)  # frame unknown: the device decides
    c = Commands(frame=(2, 50, 8000))
    with pytest.raises(CommandError, match=r"rate_hz=100 out of range: .* the device accepts 10\.\.53 Hz; for 100 Hz lower t_max_us to 3600"):
        c.set_mode(sc_mode(), 100)
    tag = c.tag
    c.set_mode(sc_mode(), 53)  # 53 x (2 x (300 + 8000) + 2200) us <= 1 s
    c.set_mode(sc_mode(), 0)  # 0 keeps the rate: nothing to check
    assert c.tag == tag + 2
    c.applied(c.set_limits(500, 10000, 100, 3600, 10000000))
    assert c.frame == (2, 50, 3600)
    c.applied(c.set_mode(sc_mode(), 100))
    assert c.frame == (2, 100, 3600)
    with pytest.raises(CommandError, match=r"t_max_us=3601 does not fit the frame with 2 channels at 100 Hz: at most 3600 us"):
        c.set_limits(500, 10000, 100, 3601, 10000000)
    with pytest.raises(CommandError, match=r"rate_hz=100 out of range: with 4 channel\(s\) and t_max_us=4000 the "
                                           r"device accepts 10\.\.51 Hz; for 100 Hz lower t_max_us to 1200 first"):
        Commands(frame=(4, 50, 4000)).set_mode(sc_mode(), 100)
    # the same rule as the device, for every rate and t_max of 4 channels
    c4 = Commands(frame=(4, 50, 1000))
    for rate in (10, 33, 50, 100):
        for t_max in (100, 1200, 1201, 1800, 1801, 4150, 4151, 8000):
            c4.frame = (4, rate, 1000)
            try:
                c4.set_limits(100, 10000, 100, t_max, 10000000)
                ok = True
            except CommandError:
                ok = False
            assert ok == hp.frame_fits(rate, 4, t_max), (rate, t_max)


def sc_mode():
    import sensation_core as sc

    return sc.MODE_AKHTAR


def test_device_learns_the_frame_from_info_and_refuses_before_sending():
    """Device.info() teaches its Commands the frame; a rate that cannot fit is then
    refused on the host (no report written); an accepted SET_LIMITS moves t_max."""
    import pytest

    from steadytouch.device import Device
    from steadytouch.protocol import CommandError
    from steadytouch.transport import open_transport

    d = Device(open_transport("sim://steady?channels=2"))  # real time: the device's keep-alive watches
    try:
        info = d.info()
        assert d.cmds.frame == (2, 50, info.t_max_us) == (2, 50, 8000)
        with pytest.raises(CommandError, match="rate_hz=100 out of range: .* accepts 10..53 Hz"):
            d.mode(sc_mode(), 100)
        d.limits(500, info.hard_i_max_ua, 100, 3600, info.hard_q_max_pc)  # up to the hard limits it reports
        assert d.cmds.frame == (2, 50, 3600)
        d.mode(sc_mode(), 100)
        assert d.cmds.frame == (2, 100, 3600) and d.info().rate_hz == 100
    finally:
        d.t.close()


def test_commands_beyond_the_first_wait_when_the_frame_has_no_time_left():
    """The first waiting command is always served; more only while hp.FRAME_CMD_US
    remain before the next deadline; the others are served in the next frames."""
    _, res, _ = run_fw("""
        s, board, usb, clock = make("steady", n=2)
        start(s, t0=1000)
        s.run(2)
        usb.sent.clear()
        def acks():
            n = sum(1 for r in usb.sent if r[0] == hp.REP_INFO)
            usb.sent.clear()
            return n
        for k in range(4):
            command(s, hp.cmd_get_info(bytearray(64), k + 1))
        s.run(1)                  # 2 ms of pulses: time for all four
        r = {"roomy": acks()}
        fire = board.fire
        def slow(ch, t):          # the pulses take the frame up to 1 ms before its end
            clock.advance(9500 - t)
            return fire(ch, t)
        board.fire = slow
        for k in range(4):
            command(s, hp.cmd_get_info(bytearray(64), k + 1))
        s.run(1)
        r["tight"] = acks()
        board.fire = fire
        s.run(1)
        r["next"] = acks()
        result(**r)
    """)
    assert res[0] == {"roomy": 4, "tight": 1, "next": 3}
