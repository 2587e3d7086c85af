"""The `steadytouch` command end to end, against sim:// (the firmware in the VM)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from steadytouch.cli import build_parser
from steadytouch.record import read_recording

from conftest import ROOT

EXE = str(Path(sys.executable).parent / "steadytouch")
AUTO = "auto=1000,1000,-1670,186000"


def run(*args, timeout=120):
    return subprocess.run([EXE, *args], capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def test_every_subcommand_has_help_with_examples():
    p = build_parser()
    subs = p._subparsers._group_actions[0].choices
    assert {"sim", "monitor", "record", "audit", "plot", "arm", "disarm", "calibrate", "limits", "mode", "info",
            "flash", "devices"} <= set(subs)
    for name, sp in subs.items():
        assert "examples:" in sp.format_help(), name


def test_record_over_sim_then_audit_is_bit_exact(tmp_path):
    out = tmp_path / "rec.csv"
    p = run("record", str(out), "--device", f"sim://peel?{AUTO}&frames=100")  # real time: 2 s
    assert p.returncode == 1 and "device lost: the simulated device stopped (exit code 0)" in p.stderr  # ran to its end
    meta, rows = read_recording(out)
    assert meta["firmware"] == "0.5.0" and meta["ch0_i0_ua"] == "1000" and meta["ch1_y_star_pc"] == "186000"
    assert (meta["ch0_skin_rs_ohm"], meta["ch0_skin_beta_q16"], meta["ch0_skin_cp_pf"]) == ("0", "0", "0")  # (none set)
    # its 100 frames count from the recording's start (sim://'s scenario waits for the session): all of
    # them recorded, and the few frames it ran while the host read its metadata before
    assert 200 <= len(rows) <= 300 and {r["channel"] for r in rows} == {0, 1}  # (the few: < 50 frames)
    a = run("audit", str(out))
    assert a.returncode == 0 and f"{len(rows)} pulses replayed through sensation_core: bit-exact" in a.stdout, \
        a.stdout + a.stderr
    # a pulse whose I differs from the law is found
    lines = out.read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if not line.startswith("#")) + 150
    cells = lines[k].split(",")
    cells[13] = str(int(cells[13]) + 1)  # next_i_ua
    lines[k] = ",".join(cells)
    out.write_text("\n".join(lines) + "\n")
    a = run("audit", str(out))
    assert a.returncode == 1 and "1 MISMATCH" in a.stdout and "row 150" in a.stdout


@pytest.mark.parametrize(
    "text, words",
    [
        ("# x: 1\nseq,time_us\n", "missing column(s) channel, i_ua"),
        (None, "malformed row"),  # a short row that is not the last: corruption, not a cut
        (None, "column rp_ohm is not a whole number"),
        ("", "no column header"),
    ],
)
def test_corrupted_or_truncated_csv_is_one_clear_line(tmp_path, text, words):
    f = tmp_path / "bad.csv"
    if text is None:
        good = run("sim", "steady", "--mode", "akhtar", "--out", str(tmp_path), "--no-plot")
        assert good.returncode == 0, good.stderr
        lines = (tmp_path / "steady-akhtar.csv").read_text().splitlines()
        if "malformed" in words:
            lines[-3] = lines[-3][: len(lines[-3]) // 2]
        else:
            c = lines[-5].split(",")
            c[6] = "12k"
            lines[-5] = ",".join(c)
        text = "\n".join(lines)
    f.write_text(text)
    p = run("audit", str(f))
    assert p.returncode == 2 and words in p.stderr and "Traceback" not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1


def test_audit_of_a_cut_recording_audits_its_complete_rows_and_says_where(tmp_path):
    good = run("sim", "steady", "--mode", "akhtar", "--out", str(tmp_path), "--no-plot")
    assert good.returncode == 0, good.stderr
    text = (tmp_path / "steady-akhtar.csv").read_text()
    lines = text.splitlines()
    for cut in (len(text) - 7, len(text) - len(lines[-1]) - 3):  # inside the last row, inside the one before
        f = tmp_path / "cut.csv"
        f.write_text(text[:cut])
        n = len(text[:cut].splitlines())
        p = run("audit", str(f))
        assert p.returncode == 0, p.stderr
        assert f"cut short at line {n}" in p.stdout and "bit-exact" in p.stdout


def test_ctrl_c_during_record_leaves_a_readable_file(tmp_path):
    out = tmp_path / "rec.csv"
    p = subprocess.Popen([EXE, "record", str(out), "--device", f"sim://steady?{AUTO}"], cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 30
    while time.time() < deadline and (not out.exists() or out.stat().st_size < 3000):
        time.sleep(0.2)
    time.sleep(1.5)
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=20)
    assert p.returncode == 0, stderr
    assert "saved" in stdout
    meta, rows = read_recording(out)
    assert len(rows) >= 100  # ~2 s at 50 Hz x 2 channels
    assert run("audit", str(out)).returncode == 0


def test_device_commands_over_sim():
    url = "sim://steady?channels=2"
    p = run("info", "--device", url)
    assert p.returncode == 0 and "steadytouch firmware 0.5.0 on pico-stmisola, 2 channel(s)" in p.stdout
    assert "ch0: not calibrated" in p.stdout
    p = run("arm", "--device", url)
    assert p.returncode == 2 and "arm: not calibrated (send calibrate first)" in p.stderr
    p = run("calibrate", "--device", url, "--i0-ua", "50000", "--t0-us", "1000", "--x-star-ohm", "-1670", "--y-star-pc", "0")
    assert p.returncode == 2 and "i0_ua=50000 out of range: the device accepts 1..20000 uA" in p.stderr  # the host's check
    from steadytouch.device import Device
    from steadytouch.transport import open_transport

    with open_transport(url) as t:  # the limits the device reports (the realistic board without a DAC gain holds
        info = Device(t).info()     # them at 9650 uA: docs/safety.md, "no DAC gain known")
    p = run("calibrate", "--device", url, "--i0-ua", "15000", "--t0-us", "100", "--x-star-ohm", "-1670", "--y-star-pc", "0")
    assert p.returncode == 2 and f"i0_ua=15000 out of range: the device's soft limits are 500..{info.i_max_ua} uA" in p.stderr
    p = run("calibrate", "--device", url, "--i0-ua", "1000")
    assert p.returncode == 2 and "calibrate needs --t0-us, --x-star-ohm, --y-star-pc" in p.stderr
    p = run("mode", "open", "--rate-hz", "300", "--device", url)
    assert p.returncode == 2 and "rate_hz=300 out of range: the device accepts 10..100 Hz" in p.stderr
    p = run("limits", "--device", url, "--i-min-ua", "500", "--i-max-ua", "20000", "--t-min-us", "100",
            "--t-max-us", "4000", "--q-max-pc", "5000000")  # refused on the host against the hard limit it reports
    assert p.returncode == 2 and f"i_max_ua=20000 out of range: the device accepts 1..{info.hard_i_max_ua} uA" in p.stderr


def test_calibrate_from_json_then_arm(tmp_path):
    from steadytouch.device import Device
    from steadytouch.transport import open_transport

    j = tmp_path / "calibration.json"
    j.write_text('{"x_star_ohm": -1650.4, "y_star_pc": 180000}')
    with open_transport("sim://steady?channels=1") as t:
        d = Device(t)
        d.info()
    # the CLI opens its own simulated device; check it accepts the JSON
    p = run("calibrate", "--device", "sim://steady?channels=1", "--from", str(j), "--i0-ua", "900", "--t0-us", "800")
    assert p.returncode == 0 and "calibrate: ok" in p.stdout and "x* -1650 ohm" in p.stdout


def test_a_write_after_the_simulated_device_ran_its_frames_says_why_it_stopped():
    # the CI race of session 29: the device ended its frames between the host's last read and its
    # next write (a keep-alive), and the write's broken pipe lost the exit code a read would give
    import hid_protocol as hp
    from steadytouch.transport import Disconnected, open_transport

    t = open_transport("sim://steady?channels=1&realtime=0&frames=3")
    try:
        assert t.p.wait(timeout=60) == 0  # ran its 3 frames, exited
        with pytest.raises(Disconnected) as e:
            t.write(bytes(hp.REPORT_LEN))
        assert "the simulated device stopped (exit code 0): it ran its frames" in str(e.value)
    finally:
        t.close()


def test_bad_device_url_is_one_line():
    p = run("info", "--device", "tcp://nowhere")
    assert p.returncode == 2 and p.stderr.startswith("steadytouch: unknown device") and "Traceback" not in p.stderr
    p = run("info", "--device", "sim://nosuch")
    assert p.returncode == 2 and "unknown scenario 'nosuch'" in p.stderr


def test_monitor_shows_every_channel(tmp_path):
    p = run("monitor", "--seconds", "1.5", "--device", f"sim://peel?{AUTO}")
    assert p.returncode == 0, p.stderr
    assert "steadytouch monitor" in p.stdout and "\n 0 stimulating" in p.stdout and "\n 1 stimulating" in p.stdout
    assert "tau us" in p.stdout.splitlines()[1]  # the skin's tau after each pulse (telemetry ltau_q16)


def test_monitor_plot_without_a_display_is_one_line():
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    p = subprocess.run([EXE, "monitor", "--plot", "--seconds", "1", "--device", "sim://steady"], capture_output=True,
                       text=True, timeout=60, cwd=ROOT, env=env)
    assert p.returncode == 2 and "--plot needs a display" in p.stderr and "Traceback" not in p.stderr


def test_flash_dry_run_lists_files_and_commands(tmp_path):  # more in tests/flash/
    p = subprocess.run([EXE, "flash", "--dry-run", "--online", "--build-dir", str(tmp_path / "dev")], cwd=ROOT,
                       capture_output=True, text=True, timeout=120, env=dict(os.environ, XDG_CACHE_HOME=str(tmp_path)))
    assert p.returncode == 0, p.stderr
    assert "sensation_core.mpy" in p.stdout and "stim.mpy" in p.stdout and "main.py" in p.stdout
    assert "board_sim" not in p.stdout and "would download usb-device 0.2.1 + usb-device-hid 0.1.2" in p.stdout


def test_sim_writes_csv_png_and_summary(tmp_path):
    p = run("sim", "peel", "--out", str(tmp_path))
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "peel-akhtar.csv").exists() and (tmp_path / "peel-open.csv").exists()
    png = (tmp_path / "peel.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20000
    assert "mQ err akhtar" in p.stdout and "(bound)" in p.stdout
    p2 = run("plot", str(tmp_path / "peel-akhtar.csv"), "--planes", "--out", str(tmp_path / "x.png"))
    assert p2.returncode == 0 and (tmp_path / "x-planes.png").exists()


def test_sim_reports_progress_in_simulated_time():
    from steadytouch.simrun import Calib, run_firmware

    seen = []
    reps = run_firmware("exercise", "akhtar", Calib(), frames=6000, progress=seen.append)
    assert len(reps) == 3 + 1 + 6000  # the --auto start's three acks and its GET_INFO answer, then the telemetry
    assert seen and seen == sorted(seen) and 0 <= seen[-1] <= 120.0


def test_skin_fits_calibration_pulses_and_sends_them(tmp_path):
    """`steadytouch skin`: the electrode model from pulses read on the simulated skin (its
    own parameters come back), sent to the simulated device; a bad file is one line."""
    import sys

    sys.path.insert(0, str(ROOT / "firmware"))
    from sim_electrode import Electrode

    from steadytouch import skin

    e = Electrode()
    f = tmp_path / "pulses.csv"
    f.write_text("i_ua,t_us,rp_ohm\n" + "".join(
        f"{i},{t},{round(e.rp_kohm(i, t) * 1000)}\n" for i, t in skin.sweep(1000, 1000)))
    p = run("skin", str(f), "--send", "--device", "sim://steady")
    assert p.returncode == 0, p.stdout + p.stderr
    m = skin.fit(skin.load(f))
    assert abs(m.rs_ohm - e.rs * 1000) <= 5 and abs(m.beta - e.beta) < 0.002 and abs(m.cp_pf - e.c * e.area0 * 1000) < 50
    assert f"Cp {m.cp_pf} pF" in p.stdout and "sim://steady: skin: ok" in p.stdout
    bad = tmp_path / "bad.csv"
    bad.write_text("i_ua,t_us,rp_ohm\n1000,1000,abc\n")
    p = run("skin", str(bad))
    assert p.returncode != 0 and "bad.csv row 2: column rp_ohm is not a number: 'abc'" in p.stderr
    assert "Traceback" not in p.stderr


def test_info_shows_a_channels_skin_model(monkeypatch, capsys):
    """Firmware 0.4.1: the Calibration report carries the skin model set; `info` shows it per channel."""
    import contextlib

    from steadytouch import cli
    from steadytouch.device import Device
    from steadytouch.transport import open_transport

    url = "sim://steady?channels=2"
    with open_transport(url) as t:
        assert Device(t).skin(500, 36045, 14000, ch=1).ok
        monkeypatch.setattr(cli, "open_transport", lambda u: contextlib.nullcontext(t))
        assert cli.main(["info", "--device", url]) == 0
        out = capsys.readouterr().out
        assert "ch1: skin model Rs 500 ohm, beta 0.550, Cp 14000 pF; tau not read" in out, out
        assert "ch0: skin model" not in out, out
        assert Device(t).skin(500, 36045, 14000, ch=1, tau_q16=-5000).ok  # (firmware 0.5.0: rule 7's gain)
        assert cli.main(["info", "--device", url]) == 0
    out = capsys.readouterr().out
    assert "ch1: skin model Rs 500 ohm, beta 0.550, Cp 14000 pF; tau read x 0.948 (rule 7)" in out, out


def test_a_fast_run_with_skin_models_and_a_tau_gain_records_and_audits_bit_exact(tmp_path, monkeypatch, capsys):
    """End to end through sim:// (firmware 0.5.0): two channels with different skin models, channel 0 with rule
    7's tau gain; `record --arm` writes each channel's model and gain into the header (GET_INFO's Calibration
    report) and `audit` replays the gel step bit-exact from it. Without the header's gain the replay parts from
    the device (the check can fail)."""
    import contextlib

    from steadytouch import cli
    from steadytouch.audit import audit
    from steadytouch.device import Device
    from steadytouch.transport import open_transport

    import sensation_core as sc

    url = "sim://gel-step?channels=2&mode=fast"
    out = tmp_path / "rec.csv"
    with open_transport(url) as t:
        d = Device(t)
        assert d.skin(500, 36045, 14000, ch=0, tau_q16=-1500).ok and d.skin(800, 40000, 20000, ch=1).ok
        assert d.mode(sc.MODE_FAST).ok and d.calibrate(1000, 1000, -1670, 186000).ok
        monkeypatch.setattr(cli, "open_transport", lambda u: contextlib.nullcontext(t))
        cli.main(["record", str(out), "--device", url, "--arm", "--seconds", "3"])
    meta, rows = read_recording(out)
    assert meta["firmware"] == "0.5.0" and meta["ch0_skin_tau_q16"] == "-1500"
    assert meta["ch1_skin_tau_q16"] == str(sc.SKIN_TAU_OFF) and meta["ch1_skin_cp_pf"] == "20000"
    assert {r["mode"] for r in rows} == {sc.MODE_FAST} and len(rows) > 150, len(rows)
    r = audit(meta, rows)
    assert r.checked > 150 and not r.mismatches and not r.no_skin, r.mismatches[:3]
    assert audit({**meta, "ch0_skin_tau_q16": str(sc.SKIN_TAU_OFF)}, rows).mismatches
