"""`steadytouch sweep`: calibration sweeps measured on the (simulated) device, written as read,
fitted as `skin` fits them; the device's mode and the channel's calibration put back."""

import csv
import subprocess
import sys
from pathlib import Path

import pytest

import hid_protocol as hp
import sensation_core as sc

from conftest import FIRMWARE, ROOT

sys.path.insert(0, str(FIRMWARE))  # sim_electrode: sim://'s electrode

EXE = str(Path(sys.executable).parent / "steadytouch")


def run(*args, timeout=120):
    return subprocess.run([EXE, *args], capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def rows_of(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_a_sweep_on_the_simulated_device_writes_every_pulse_and_fits_them(tmp_path):
    from sim_electrode import Electrode
    from steadytouch import skin

    out = tmp_path / "sweeps.csv"
    p = run("sweep", str(out), "--device", "sim://steady", "--i0-ua", "1000", "--t0-us", "1000", "--sweeps", "3",
            "--send")  # real time: ~6 s
    assert p.returncode == 0, p.stdout + p.stderr
    rows = rows_of(out)
    pts = skin.sweep_wide(1000, 1000)
    assert list(rows[0]) == ["sweep", "i_ua", "t_us", "rp_ohm", "ltau_q16"] and len(rows) == 3 * len(pts)
    assert [(int(r["i_ua"]), int(r["t_us"])) for r in rows] == pts * 3 and [int(r["sweep"]) for r in rows[::11]] == [0, 1, 2]
    e = Electrode()  # sim://steady's electrode, read through the realistic board (monitor gain and offset, noise)
    for r in rows:
        true = e.rp_kohm(int(r["i_ua"]), int(r["t_us"])) * 1000
        assert abs(int(r["rp_ohm"]) / true - 1) < 0.05, r
    assert sum(int(r["ltau_q16"]) > 0 for r in rows) > len(rows) // 2  # the decay's tau after most pulses
    assert "3 sweeps averaged" in p.stdout and "sim://steady: skin: ok" in p.stdout


def test_sweep_puts_the_mode_and_the_channels_calibration_back_and_more_adds_to_the_file(tmp_path, monkeypatch):
    from steadytouch import cli, skin
    from steadytouch.device import Device
    from steadytouch.transport import open_transport

    t = open_transport("sim://steady?channels=2")

    class Kept:  # the CLI's transport is this one, left open for the checks after it
        def __enter__(self):
            return t

        def __exit__(self, *exc):
            return False

    monkeypatch.setattr(cli, "open_transport", lambda url: Kept())
    out = tmp_path / "s.csv"
    try:
        d = Device(t)
        d.mode(sc.MODE_AKHTAR)
        d.calibrate(1200, 900, -1670, 186000, ch=0)
        d.calibrate(1000, 1000, -1670, 186000, ch=1)
        assert cli.main(["sweep", str(out), "--device", "sim://steady", "--sweeps", "3"]) == 0  # I0, T0: ch 0's
        c0, c1, info = d.calibration(0), d.calibration(1), d.info()
        assert (c0.i0_ua, c0.t0_us, c0.x_star_ohm, c0.y_star_pc) == (1200, 900, -1670, 186000)
        assert (c1.i0_ua, c1.t0_us) == (1000, 1000) and info.mode == sc.MODE_AKHTAR
        rows = rows_of(out)
        pts = skin.sweep_wide(1200, 900)  # 12 pulses: 900 us is not one of its durations
        assert [(int(r["i_ua"]), int(r["t_us"])) for r in rows] == pts * 3
        assert cli.main(["sweep", str(out), "--device", "sim://steady", "--sweeps", "3", "--more"]) == 0
        rows = rows_of(out)
        assert len(rows) == 6 * len(pts) and sorted({int(r["sweep"]) for r in rows}) == list(range(6))
    finally:
        t.close()


def test_sweep_refuses_bad_input_before_any_pulse(tmp_path):
    out = tmp_path / "s.csv"
    p = run("sweep", str(out), "--device", "sim://steady", "--i0-ua", "1000", "--t0-us", "1000", "--sweeps", "2")
    assert p.returncode == 2 and "--sweeps 2 out of range: 3..60" in p.stderr and "Traceback" not in p.stderr
    p = run("sweep", str(out), "--device", "sim://steady", "--i0-ua", "4000", "--t0-us", "1000")
    assert p.returncode == 2 and "outside the limits in force" in p.stderr and "Traceback" not in p.stderr, p.stderr
    assert not out.exists()  # nothing pulsed, nothing written
    p = run("sweep", str(out), "--device", "sim://steady", "--channel", "3", "--i0-ua", "1000", "--t0-us", "1000")
    assert p.returncode == 2 and "channel 3" in p.stderr and "Traceback" not in p.stderr, p.stderr
    p = run("sweep", str(out), "--device", "sim://steady", "--more")
    assert p.returncode == 2 and "--more adds sweeps to a file" in p.stderr
    out.write_text("x\n")
    p = run("sweep", str(out), "--device", "sim://steady", "--i0-ua", "1000", "--t0-us", "1000")
    assert p.returncode == 2 and "exists" in p.stderr and out.read_text() == "x\n"


def test_skin_leaves_out_an_unfinished_last_sweep(tmp_path):
    from sim_electrode import Electrode
    from steadytouch import skin

    e = Electrode()
    pts = skin.sweep_wide(1000, 1000)
    lines = ["sweep,i_ua,t_us,rp_ohm"] + [f"{k},{i},{t},{round(e.rp_kohm(i, t) * 1000 * (1 + 0.001 * ((k + j) % 3 - 1)))}"
                                         for k in range(4) for j, (i, t) in enumerate(pts)][:3 * len(pts) + 4]
    f = tmp_path / "cut.csv"
    f.write_text("\n".join(lines) + "\n")
    p = run("skin", str(f))
    assert p.returncode == 0, p.stdout + p.stderr
    assert "sweep 4 of 4 has 4 of its 11 pulses (an interrupted recording): left out" in p.stdout
    assert "3 sweeps averaged" in p.stdout
    # then `sweep --more` adds whole sweeps after the cut one
    more = [f"{k},{i},{t},{round(e.rp_kohm(i, t) * 1000)}" for k in (4, 5) for i, t in pts]
    f.write_text("\n".join(lines + more) + "\n")
    p = run("skin", str(f))
    assert p.returncode == 0 and "sweep 4 of 6 has 4 of its 11 pulses" in p.stdout and "5 sweeps averaged" in p.stdout, \
        p.stdout + p.stderr
