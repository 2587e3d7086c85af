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
