"""LSL outlets of `record --lsl` and `sim --lsl`, received by an inlet on this machine
(LSLAPICFG: the loopback configuration, see conftest.lsl)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import uuid
import xml.etree.ElementTree as ET

import pytest

import hid_protocol as hp

from steadytouch.lsl.streams import STOP_REASONS, unit
from steadytouch.record import COLUMNS, CUT, read_recording

from .conftest import pull_all, steadytouch

AUTO = "1000,1000,-1670,186000"


def _desc(xml: str):
    root = ET.fromstring(xml)
    return root, root.find("desc")


def _check_layout_and_meta(xml: str, meta: dict, n_channels: int):
    root, d = _desc(xml)
    assert root.findtext("type") == "StimTelemetry"
    assert root.findtext("channel_format") == "int32"
    assert int(root.findtext("channel_count")) == len(COLUMNS)
    chans = d.find("channels").findall("channel")
    assert [c.findtext("label") for c in chans] == COLUMNS  # exactly the CSV's columns, in order
    assert [c.findtext("unit") for c in chans] == [unit(c) for c in COLUMNS]
    units = dict(zip(COLUMNS, (c.findtext("unit") for c in chans)))
    assert (units["i_ua"], units["t_us"], units["vp_mv"], units["rp_ohm"], units["me_ua2ms"],
            units["mq_target_fc_per_ohm"]) == ("uA", "us", "mV", "ohm", "uA^2*ms", "fC/ohm")
    dev = d.find("device")
    assert dev.findtext("firmware") == meta["firmware"]
    assert dev.findtext("serial") == meta["serial"]
    assert dev.findtext("n_channels") == str(n_channels)
    assert d.findtext("mode") == meta["mode"]
    lim = d.find("limits")
    for k in ("i_min_ua", "i_max_ua", "t_min_us", "t_max_us", "q_max_pc"):
        assert lim.findtext(k) == str(meta[k]), k
    cal = d.find("calibration").findall("channel")
    assert [int(c.findtext("index")) for c in cal] == list(range(n_channels))
    for k in ("hard_i_max_ua", "hard_t_max_us", "hard_q_max_pc", "compliance_mv"):
        if k in meta:  # a device's (record, monitor); sim's metadata has the soft limits only
            assert lim.findtext(k) == str(meta[k]), k
    for c in cal:
        ch = c.findtext("index")
        for k in ("i0_ua", "t0_us", "x_star_ohm", "y_star_pc"):  # every one present and equal
            assert c.findtext(k) == str(meta.get(f"ch{ch}_{k}", meta.get(k))), (ch, k)
        # measured at the first pulse after arm: the device's value when the stream opened (0: not yet)
        assert c.findtext("rp0_ohm") == str(meta.get(f"ch{ch}_rp0_ohm", 0)), ch
    assert "minima" in d.find("clock").findtext("timestamps") or "virtual" in d.find("clock").findtext("timestamps")


LATE_S = 3.0  # a recorder that connects this long after the outlets appeared (LabRecorder's user clicking)


def _pull_late(lsl, source_id: str, proc, late_s: float = LATE_S):
    """pull_all, but the inlets connect late_s after the outlets appeared: the recording waits for
    them (--lsl-wait) while the simulated device already runs. Once made the test deterministic:
    sim://'s 8-s scenario ran from the VM's boot, so a recorder later than ~1.5 s (a loaded CI
    machine) let the device end first ("device lost ... exit code 0")."""
    import time

    assert lsl.resolve_byprop("source_id", f"{source_id}-telemetry", 1, 20), "stream not found"
    time.sleep(late_s)  # a lower bound: the recorder is at least this late, whatever the load
    return pull_all(lsl, source_id, proc)


def _device_s(rows_or_samples, i_from, i_to, t_col=None):
    """Device-clock seconds from one report to a later one (time_us wraps at 2**30)."""
    a, b = rows_or_samples[i_from], rows_or_samples[i_to]
    ta, tb = (a["time_us"], b["time_us"]) if t_col is None else (a[t_col], b[t_col])
    return ((tb - ta) % (1 << 30)) / 1e6


def _record_late(lsl, url, csv, seconds):
    """`record --lsl --arm` of url into csv for `seconds`, its recorder late (_pull_late): the
    process, what the recorder pulled (xml, samples, stamps, markers), its stdout and stderr."""
    p = steadytouch("record", str(csv), "--lsl", "--lsl-wait", "20", "--arm", "--seconds", seconds, "--device", url)
    try:
        pulled = _pull_late(lsl, f"steadytouch-{url}", p)
        out, err = p.communicate(timeout=30)
    finally:
        p.kill() if p.poll() is None else None
    return p, pulled, out, err


def test_record_lsl_equals_the_csv_and_marks_arm_stop_disarm(lsl, tmp_path):
    url = f"sim://off?channels=2&seed={uuid.uuid4().int % 100000}&auto={AUTO}"
    csv = tmp_path / "run.csv"
    p, (xml, samples, stamps, markers), out, err = _record_late(lsl, url, csv, "6.5")
    assert p.returncode == 0, err
    meta, rows = read_recording(csv)
    assert meta["serial"] == url
    _check_layout_and_meta(xml, meta, 2)

    # every pulse the inlet got equals the CSV row of the same seq, and none is missing after the first
    by_seq = {r["seq"]: [r[c] for c in COLUMNS] for r in rows}
    assert len(samples) > 400
    for s in samples:
        assert by_seq[s[0]] == s
    first = samples[0][0]
    assert [s[0] for s in samples] == [r["seq"] for r in rows if r["seq"] >= first]

    texts = [m for m, _ in markers]
    arm = texts.index("arm ch=all")
    stop0 = texts.index(f"stop ch=0 reason={STOP_REASONS[hp.STOP_ELECTRODE_OFF]}")
    disarm = texts.index("disarm ch=all")
    assert arm < stop0 < disarm, texts
    ts = dict(markers)
    assert ts["arm ch=all"] <= ts["stop ch=0 reason=electrode_off"] < ts["disarm ch=all"]
    # the stop marker sits at the first pulse report that carries the stop
    k = next(k for k, s in enumerate(samples) if s[COLUMNS.index("channel")] == 0
             and s[COLUMNS.index("stop")] == hp.STOP_ELECTRODE_OFF)
    assert abs(ts["stop ch=0 reason=electrode_off"] - stamps[k]) < 1e-9
    # timestamps follow the device clock: 20 ms frames stay 20 ms apart (the fit moves them by far less)
    t_col = COLUMNS.index("time_us")
    ch0 = [(s[t_col], t) for s, t in zip(samples, stamps) if s[2] == 0]
    gaps = [(t2 - t1) - ((d2 - d1) % (1 << 30)) / 1e6 for (d1, t1), (d2, t2) in zip(ch0, ch0[1:])]
    assert max(abs(g) for g in gaps[50:]) < 1e-3
    assert "LSL:" in out and "disarmed" in out
    # the scenario starts with the recording, not at the device's boot: the electrode comes off
    # 5.02 s into sim://off, so at least 5 s (device clock) after the first recorded pulse
    stop_row = next(k for k, r in enumerate(rows) if r["channel"] == 0 and r["stop"] == hp.STOP_ELECTRODE_OFF)
    assert _device_s(rows, 0, stop_row) >= 5.0, _device_s(rows, 0, stop_row)


def test_record_lsl_keeps_every_row_when_the_simulated_device_ends_first(lsl, tmp_path):
    """A recording longer than the simulated device runs (frames=100: 2 s), with a late recorder:
    the device's 100 frames all come after the recording started (they count from it, not from
    the boot), the host says in one stderr line that the device stopped, exits 1, and keeps every
    row: the CSV has all 100 frames of both channels, every LSL sample equals its CSV row, none is
    missing, and the closing clock marker still goes out."""
    url = f"sim://steady?channels=2&frames=100&seed={uuid.uuid4().int % 100000}&auto={AUTO}"
    csv = tmp_path / "run.csv"
    p, (xml, samples, stamps, markers), out, err = _record_late(lsl, url, csv, "30")
    assert p.returncode == 1, (out, err)
    assert err.strip().splitlines() == [err.strip()] and "Traceback" not in err
    assert "device lost: the simulated device stopped (exit code 0)" in err and "frames=N" in err, err
    meta, rows = read_recording(csv)
    assert CUT not in meta
    pulses = [r for r in rows if r["i_ua"] > 0]
    assert len(pulses) >= 200 and {r["channel"] for r in pulses} == {0, 1}, len(pulses)
    assert _device_s(rows, 0, -1) >= 1.98  # 100 frames of 20 ms, all of them recorded
    by_seq = {r["seq"]: [r[c] for c in COLUMNS] for r in rows}
    assert len(samples) >= 200 and all(by_seq[s[0]] == s for s in samples)
    assert [s[0] for s in samples] == [r["seq"] for r in rows if r["seq"] >= samples[0][0]]
    assert samples[-1][0] == rows[-1]["seq"]  # the last row went out on LSL too
    texts = [m for m, _ in markers]
    assert texts[0] == "arm ch=all" and texts[-1].startswith("clock offset_s="), texts
    assert f"saved {len(rows)} rows" in out and f"LSL: {len(samples)} samples" in out, out


def test_sim_lsl_streams_the_whole_run_on_its_virtual_clock(lsl, tmp_path):
    tag = uuid.uuid4().hex[:8]
    scen = tmp_path / f"off-{tag}.csv"  # the off scenario, under a name of this test's own
    scen.write_text("time_s,contact,hydration\n0,1,1\n3,1,1\n3.02,0,1\n4,0,1\n")
    p = steadytouch("sim", str(scen), "--mode", "akhtar", "--channels", "2", "--lsl", "--lsl-wait", "20",
                    "--no-plot", "--out", str(tmp_path))
    try:
        xml, samples, stamps, markers = pull_all(lsl, f"steadytouch-sim-off-{tag}-akhtar", p)
        out, err = p.communicate(timeout=30)
    finally:
        p.kill() if p.poll() is None else None
    assert p.returncode == 0, err
    meta, rows = read_recording(tmp_path / f"off-{tag}-akhtar.csv")
    meta["serial"] = f"sim-off-{tag}-akhtar"
    _check_layout_and_meta(xml, meta, 2)
    assert samples == [[r[c] for c in COLUMNS] for r in rows]  # all of them, in order
    t_col = COLUMNS.index("time_us")
    for (s1, t1), (s2, t2) in zip(zip(samples, stamps), zip(samples[1:], stamps[1:])):
        assert abs((t2 - t1) - (s2[t_col] - s1[t_col]) / 1e6) < 1e-6
    texts = [m for m, _ in markers]
    assert texts[:3] == ["mode akhtar rate_hz=unchanged",
                         "calibrate ch=all i0_ua=1000 t0_us=1000 x_star_ohm=-1670 y_star_pc=186000", "arm ch=all"]
    assert "stop ch=0 reason=electrode_off" in texts and "stop ch=1 reason=electrode_off" in texts
    assert texts[-1].startswith("clock virtual")


def test_lsl_without_pylsl_is_one_line_and_the_rest_works(tmp_path):
    fake = tmp_path / "nolsl"
    fake.mkdir()
    (fake / "pylsl.py").write_text("raise ImportError('No module named pylsl')\n")
    env = dict(os.environ, PYTHONPATH=str(fake))
    exe = os.path.join(os.path.dirname(sys.executable), "steadytouch")
    for args in (["record", str(tmp_path / "r.csv"), "--lsl", "--device", "sim://steady"],
                 ["sim", "steady", "--lsl", "--no-plot", "--out", str(tmp_path / "o")],
                 ["monitor", "--lsl", "--device", "sim://steady"]):
        r = subprocess.run([exe, *args], env=env, capture_output=True, text=True, timeout=60)
        assert r.returncode == 2, r
        assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
        assert "pip install" in r.stderr and "pylsl==1.18.6" in r.stderr
        assert not (tmp_path / "r.csv").exists() and not (tmp_path / "o").exists()
    r = subprocess.run([exe, "sim", "steady", "--mode", "akhtar", "--no-plot", "--out", str(tmp_path / "o")],
                       env=env, capture_output=True, text=True, timeout=120)  # without --lsl: works
    assert r.returncode == 0, r.stderr


def test_monitor_lsl_streams_and_marks_its_disarm(lsl):
    url = f"sim://steady?channels=2&seed={uuid.uuid4().int % 100000}&auto={AUTO}"
    p = steadytouch("monitor", "--lsl", "--lsl-wait", "20", "--seconds", "3", "--device", url)
    try:
        xml, samples, stamps, markers = pull_all(lsl, f"steadytouch-{url}", p)
        out, err = p.communicate(timeout=30)
    finally:
        p.kill() if p.poll() is None else None
    assert p.returncode == 0, err
    _, d = _desc(xml)
    assert [c.findtext("label") for c in d.find("channels").findall("channel")] == COLUMNS
    assert d.find("device").findtext("serial") == url and d.findtext("mode") == "akhtar"
    assert len(samples) > 150 and {s[2] for s in samples} == {0, 1}
    assert all(b >= a - 1e-3 for a, b in zip(stamps, stamps[1:]))  # in order (two channels share a frame's time)
    assert [m for m, _ in markers][-2:][0] == "disarm ch=all"
    assert "monitor:" in out and "disarmed" in out


def test_record_lsl_on_the_emulated_chip(lsl, tmp_path):
    """`record --lsl` against emu:// (the rp2 firmware on the emulated Pico, about 30-50 s here):
    the streams carry the real firmware's reports: every label, unit and metadata field, every
    sample equal to its CSV row, the arm, disarm and clock markers. Not the timestamps: the
    emulated chip's clock runs at a fraction of real time (about a third here, varying with the
    machine's load), a "drift" of several 100 000 ppm whose fit moves the timestamps by seconds
    when it first applies; that measures the emulator, not a crystal (docs/lab.md, "The clock")."""
    from steadytouch.emu import EMULATOR, NO_EMULATOR

    if not (EMULATOR / "firmware.uf2").exists():
        pytest.skip(NO_EMULATOR)
    url = f"emu://steady?channels=1&auto={AUTO}"
    csv = tmp_path / "emu.csv"
    p = steadytouch("record", str(csv), "--lsl", "--lsl-wait", "120", "--arm", "--seconds", "6", "--device", url)
    try:
        # the outlets open after the emulated Pico booted and answered: 20 s was too short once
        # in a fresh-clone CI run under load (--lsl-wait 120 keeps the device waiting that long)
        xml, samples, stamps, markers = pull_all(lsl, f"steadytouch-{url}", p, max_s=150, resolve_s=120)
        out, err = p.communicate(timeout=60)
    finally:
        p.kill() if p.poll() is None else None
    assert p.returncode == 0, err
    meta, rows = read_recording(csv)
    assert meta["serial"] == url and meta["board"] == "pico-stmisola"
    _check_layout_and_meta(xml, meta, 1)
    by_seq = {r["seq"]: [r[c] for c in COLUMNS] for r in rows}
    assert len(samples) >= 50
    assert all(by_seq[s[0]] == s for s in samples)
    assert [s[0] for s in samples] == [r["seq"] for r in rows if r["seq"] >= samples[0][0]]
    texts = [m for m, _ in markers]
    assert texts.index("arm ch=all") < texts.index("disarm ch=all") and texts[-1].startswith("clock ")
    print(f"emu: {len(samples)} samples; {texts[-1]}")  # the fit of a clock running at a fraction of real time
    assert "disarmed" in out


def test_ctrl_c_during_record_lsl_loses_nothing(lsl, tmp_path):
    """SIGINT (Ctrl-C) in the middle of `record --lsl --arm`: exit 0, the CSV complete, every
    pulse the inlet got equal to its CSV row and none missing after the first, and the closing
    `disarm` and `clock` markers still sent, after the last sample."""
    import signal
    import time

    url = f"sim://steady?channels=2&frames=3000&seed={uuid.uuid4().int % 100000}&auto={AUTO}"
    csv = tmp_path / "run.csv"
    p = steadytouch("record", str(csv), "--lsl", "--lsl-wait", "20", "--arm", "--device", url)

    def interrupt_after_3_s():
        time.sleep(3.0)
        p.send_signal(signal.SIGINT)

    import threading

    tel = lsl.resolve_byprop("source_id", f"steadytouch-{url}-telemetry", 1, 20)
    assert tel, "stream not found"
    threading.Thread(target=interrupt_after_3_s, daemon=True).start()
    try:
        xml, samples, stamps, markers = pull_all(lsl, f"steadytouch-{url}", p)
        out, err = p.communicate(timeout=30)
    finally:
        p.kill() if p.poll() is None else None
    assert p.returncode == 0 and "Traceback" not in err, err
    meta, rows = read_recording(csv)
    assert CUT not in meta and len(rows) >= 100
    assert len(samples) >= 100
    assert [s[0] for s in samples] == [r["seq"] for r in rows if r["seq"] >= samples[0][0]]
    by_seq = {r["seq"]: [r[c] for c in COLUMNS] for r in rows}
    assert all(by_seq[s[0]] == s for s in samples)
    texts = [m for m, _ in markers]
    assert texts[-2] == "disarm ch=all" and texts[-1].startswith("clock offset_s="), texts
    assert markers[-2][1] >= stamps[-1] - 0.05
    assert re.search(r"record: \d+ pulses on 2 channel\(s\) in [\d.]+ s", out) and f"{url}: disarmed" in out
    assert f"LSL: {len(samples)} samples on 'steadytouch telemetry'" in out, out  # all it pushed arrived
