"""Configurations whose worst-case frame cannot fit its period are refused
(hid_protocol.frame_fits: rate x channels x (t_max + compute) <= 1 s)."""

import hid_protocol as hp
from fw_harness import run_fw


def test_rule_numbers():
    assert hp.frame_fits(50, 4, 4000) and not hp.frame_fits(50, 4, 4001)
    assert hp.frame_fits(100, 2, 4000) and not hp.frame_fits(100, 2, 4001)
    assert hp.frame_fits(50, 2, 8000)
    assert hp.t_max_fitting(50, 4) == 4000 and hp.t_max_fitting(100, 4) == 1500


def test_device_refuses_a_frame_that_cannot_fit():
    _, res, _ = run_fw("""
        s, board, usb, clock = make("steady", n=2)
        b = bytearray(64)
        r = {"boot_t_max": s.lim[3]}
        r["rate100"] = apply(s, hp.cmd_set_mode(b, sc.MODE_AKHTAR, 100))
        r["detail100"] = s.tx[hp.O_DETAIL]
        r["rate_after"] = s.rate_hz
        r["lim4001"] = apply(s, hp.cmd_set_limits(b, 500, 10000, 100, 4001, 10000000))
        r["lim4000"] = apply(s, hp.cmd_set_limits(b, 500, 10000, 100, 4000, 10000000))
        r["rate100b"] = apply(s, hp.cmd_set_mode(b, sc.MODE_AKHTAR, 100))
        r["lim5000"] = apply(s, hp.cmd_set_limits(b, 500, 10000, 100, 5000, 10000000))
        r["detail5000"] = s.tx[hp.O_DETAIL]
        s4, _, _, _ = make("steady", n=4)
        r["boot4_t_max"] = s4.lim[3]
        result(**r)
    """)
    r = res[0]
    assert r["boot_t_max"] == 8000  # 2 x (8000 + 1000) us fits 20 ms
    assert r["rate100"] == hp.RES_OUT_OF_RANGE and r["detail100"] == hp.O_ARG + 1 and r["rate_after"] == 50
    assert r["lim4001"] == hp.RES_OK  # at 50 Hz it fits
    assert r["lim4000"] == hp.RES_OK and r["rate100b"] == hp.RES_OK
    assert r["lim5000"] == hp.RES_OUT_OF_RANGE and r["detail5000"] == hp.O_ARG + 6  # at 100 Hz it does not
    assert r["boot4_t_max"] == 4000  # 4 channels at 50 Hz: the default t_max lowered to fit


def test_host_refuses_a_rate_or_t_max_whose_frame_cannot_fit():
    """host/protocol.Commands applies the device's rule once it knows the frame
    (from GET_INFO, then every acknowledged SET_MODE/SET_LIMITS): one clear
    CommandError naming the largest value that fits, no report built."""
    import pytest

    from steadytouch.protocol import CommandError, Commands

    c = Commands()
    c.set_mode(sc_mode(), 100)  # frame unknown: the device decides
    c = Commands(frame=(2, 50, 8000))
    with pytest.raises(CommandError, match=r"rate_hz=100 does not fit .* at most 55 Hz, or lower t_max_us to 4000"):
        c.set_mode(sc_mode(), 100)
    tag = c.tag
    c.set_mode(sc_mode(), 55)  # 55 x 2 x 9000 us <= 1 s
    c.set_mode(sc_mode(), 0)  # 0 keeps the rate: nothing to check
    assert c.tag == tag + 2
    c.applied(c.set_limits(500, 10000, 100, 4000, 10000000))
    assert c.frame == (2, 50, 4000)
    c.applied(c.set_mode(sc_mode(), 100))
    assert c.frame == (2, 100, 4000)
    with pytest.raises(CommandError, match=r"t_max_us=4001 does not fit the frame with 2 channels at 100 Hz: at most 4000 us"):
        c.set_limits(500, 10000, 100, 4001, 10000000)
    # the same rule as the device, for every rate and t_max of 4 channels
    c4 = Commands(frame=(4, 50, 1000))
    for rate in (10, 33, 50, 100):
        for t_max in (100, 1500, 1501, 4000, 4001, 8000):
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
        with pytest.raises(CommandError, match="rate_hz=100 does not fit"):
            d.mode(sc_mode(), 100)
        d.limits(500, 10000, 100, 4000, 10000000)
        assert d.cmds.frame == (2, 50, 4000)
        d.mode(sc_mode(), 100)
        assert d.cmds.frame == (2, 100, 4000) and d.info().rate_hz == 100
    finally:
        d.t.close()
