"""`steadytouch mode --rate-hz`: every rate from 10 to 100 is not always possible: the frame (each
channel's pulse of up to t_max and its work) must fit the period. A rate that does not fit was
"mode: value out of range (byte 5)"; now the accepted range for the device's channels and t_max."""

import subprocess
import sys
from pathlib import Path

import pytest
import sensation_core as sc

from steadytouch.cli import build_parser
from steadytouch.device import Device, DeviceError
from steadytouch.transport import open_transport

from conftest import ROOT

EXE = str(Path(sys.executable).parent / "steadytouch")


def run(*args):
    return subprocess.run([EXE, *args], capture_output=True, text=True, timeout=120, cwd=ROOT)


@pytest.mark.parametrize("url, rate, top", [("sim://steady", 55, 53), ("sim://steady", 100, 53),
                                            ("sim://steady?channels=1", 100, 95)])
def test_a_rate_the_frame_cannot_fit_names_the_accepted_range(url, rate, top):
    n = 1 if "channels=1" in url else 2
    p = run("mode", "akhtar", "--device", url, "--rate-hz", str(rate))
    err = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(err) == 1 and "Traceback" not in p.stderr, p.stderr
    assert f"rate_hz={rate} out of range: with {n} channel(s) and t_max_us=8000 the device accepts 10..{top} Hz" \
        in err[0], err
    assert run("mode", "akhtar", "--device", url, "--rate-hz", str(top)).returncode == 0


def test_the_devices_own_refusal_of_a_rate_names_the_range():
    """A skin model set on the device that this host does not know of (another session's): the device refuses
    a rate the host let through; its ack is put in words with the ranges."""
    with open_transport("sim://steady") as t:
        d = Device(t)
        d.info()
        d.skin(200, 40000, 100000)
        d.cmds.model = 0  # as a host that did not set it
        with pytest.raises(DeviceError, match=r"rate_hz=52 out of range: the device refused it; with 2 channel\(s\) "
                                              r"and t_max_us=8000 it accepts 10\.\.53 Hz, 10\.\.51 Hz with a skin model"):
            d.mode(sc.MODE_AKHTAR, 52)


def test_the_help_example_for_100_hz_works():
    h = build_parser()._subparsers._group_actions[0].choices["mode"].format_help()
    assert "--t-max-us 3600" in h and "--rate-hz 100" in h and "at most 53 Hz" in " ".join(h.split())
    with open_transport("sim://steady") as t:
        d = Device(t)
        assert d.limits(500, 5000, 100, 3600, 5000000).ok
        assert d.mode(sc.MODE_OPEN_LOOP, 100).ok
