"""emu://: the host's commands against the real rp2 firmware on the emulated Pico
(host/emu, ../shared/emulator), the simulated electrode on its ADC."""

import os
import re
import subprocess
import sys

import pytest

import hid_protocol as hp

from steadytouch.cli import main
from steadytouch.emu import EMULATOR, NO_EMULATOR
from steadytouch.record import read_recording
from steadytouch.simrun import firmware_module

needs_emulator = pytest.mark.skipif(not (EMULATOR / "firmware.uf2").exists(), reason=NO_EMULATOR)


def test_no_emulator_is_one_line_naming_how_to_get_it(tmp_path):
    p = subprocess.run([sys.executable, "-m", "steadytouch.cli", "info", "--device", "emu://steady"],
                       env=dict(os.environ, CHIP_EMULATOR=str(tmp_path)), capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1 and "build-firmware.sh" in p.stderr
AUTO = "auto=1000,1000,-1670,186000"


@needs_emulator
def test_info_prints_the_firmware_version_and_limits(capsys):
    assert main(["info", "--device", "emu://steady"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"steadytouch firmware \d+\.\d+\.\d+ on pico-stmisola, 2 channel", out)
    # a fresh emulated board has no DAC gain stored: its hard current limit is held x 0.965, and info says why
    held = 10000 * hp.VMON_DAC_PPM_MIN // 1000000
    assert f"hard limits: I <= {held} uA" in out and "(held)" in out and "ch0: not calibrated" in out
    assert "no DAC gain was measured" in out and "--scope" in out


@needs_emulator
def test_monitor_shows_rp_close_to_the_model(capsys):
    assert main(["monitor", "--device", f"emu://steady?{AUTO}", "--arm", "--seconds", "3"]) == 0
    out = capsys.readouterr().out
    rows = re.findall(r"^\s*([01]) stimulating\S*\s+(?:\(held\)\s+)?(\d+)\s+(\d+)\s+\d+\s+(\d+)", out, re.M)
    assert {r[0] for r in rows} == {"0", "1"}, out
    e = firmware_module("sim_electrode")
    for _ch, i_ua, t_us, rp in rows:
        model = e.Electrode().rp_kohm(int(i_ua), int(t_us)) * 1000
        assert abs(int(rp) - model) < 0.03 * model
    assert "disarmed" in out


@needs_emulator
def test_calibrate_then_record_arm_is_accepted_by_audit(tmp_path, capsys):
    assert main(["calibrate", "--device", "emu://steady", "--i0-ua", "1000", "--t0-us", "1000",
                 "--x-star-ohm", "-1670", "--y-star-pc", "186000"]) == 0
    assert "ok" in capsys.readouterr().out
    f = tmp_path / "run.csv"
    assert main(["record", str(f), "--device", f"emu://gel-step?channels=1&{AUTO}", "--arm", "--seconds", "3"]) == 0
    meta, rows = read_recording(f)
    assert meta["board"] == "pico-stmisola" and len([r for r in rows]) >= 20
    capsys.readouterr()
    assert main(["audit", str(f)]) == 0
    assert "bit-exact" in capsys.readouterr().out


@needs_emulator
def test_no_node_is_one_clear_error(monkeypatch, capsys):
    monkeypatch.setenv("PATH", "/nonexistent")
    assert main(["info", "--device", "emu://steady"]) == 2
    assert "Node" in capsys.readouterr().err


@needs_emulator
def test_the_emulator_dying_is_disconnected_with_its_reason():
    from steadytouch.transport import Disconnected, open_transport

    with open_transport("emu://steady") as t:
        t.host.p.kill()
        with pytest.raises(Disconnected, match="the emulated Pico stopped"):
            while True:
                t.read(1.0)


@needs_emulator
def test_selftest_on_the_emulated_pico_stores_the_correction_on_the_device_and_reads_it_back(capsys):
    """The self-test over HID on the real firmware: the raw monitor measured (the correction off
    in RAM), CMD_SET_VMON ... VMON_STORE written to the board's flash from the running loop, read
    back with GET_INFO, the worst Rp error measured again with it (tests/chip/test_chip_vmon.py:
    the stored file survives a reset)."""
    assert main(["selftest", "--load-ohm", "10000", "--device", "emu://steady", "--pulses", "3"]) == 0
    out = capsys.readouterr().out
    back = re.search(r"read back: ch0 (\d+) ppm ([+-]\d+) mV, ch1 (\d+) ppm ([+-]\d+) mV", out)
    assert back, out
    bs = firmware_module("board_sim")
    for k in (0, 1):  # the realistic board (emu:// default): board_sim's DAC x monitor gain and offset
        row = next(ln for ln in out.splitlines() if ln.strip().startswith(f"{k} |"))
        g = float(row.split("|")[2])
        assert abs(g - bs.DAC_GAIN[k] * bs.MON_GAIN[k]) < 0.003, (k, g)
        # what was stored is what was fitted (g as the table prints it, to 4 decimals: within half its last
        # digit, plus the float error of that half: a stored 1.01235 printed as 1.0123 failed at 5.00000000001e-05)
        assert abs(int(back.group(1 + 2 * k)) / 1e6 - g) <= 0.00005 + 1e-9
        # the offset found: the monitor's, plus the peak search's noise bias (a few counts, > 0)
        assert 0 < int(back.group(2 + 2 * k)) - bs.MON_OFFSET_MV[k] < 6 * 27 * bs.ADC_NOISE_COUNTS / 2
    before = float(out.split("(was ")[1].split("%")[0])
    after = float(out.split("with the stored correction: worst Rp error ")[1].split("%")[0])
    assert after < before


@pytest.mark.parametrize("url, words", [("emu://steady?load=5", "load=5 ohm out of range [100, 1000000]"),
                                        ("emu://steady?board=perfect", "board is real (the parts' errors, default)")])
def test_emu_url_load_and_board_are_checked_in_one_line(capsys, url, words):
    assert main(["info", "--device", url]) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1


@needs_emulator
def test_the_ideal_switch_reaches_the_emulated_board():
    """emu://...?board=ideal: the emulated analog path as before (exact gains, 1.5 counts of
    noise); the default is the realistic one (board_sim's errors fed to the emulated ADC)."""
    from steadytouch.device import Device
    from steadytouch.protocol import Telemetry
    from steadytouch.transport import open_transport

    rps = {}
    for board in ("ideal", "real"):
        with open_transport(f"emu://steady?load=10000&board={board}&{AUTO}") as t:
            d = Device(t)
            got = []
            with d.live(arm=0):
                while len(got) < 15:
                    r = d.read(5)
                    if isinstance(r, Telemetry) and r.channel == 0 and r.i_ua:
                        got.append(r.rp_ohm)
            rps[board] = sorted(got)[len(got) // 2]
    assert abs(rps["ideal"] - 10000) < 100  # the peak search's noise bias only
    assert rps["real"] - 10000 > 150  # ch0: path gain 1.009 and +160 mV offset
