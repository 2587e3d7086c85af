"""Shutdown of the commands that keep a device armed (monitor, record) under
SIGINT, SIGTERM and SIGKILL, against the simulated device (sim://): the device
is disarmed (or gone with its host), the recording is readable and audits
clean, and the simulated device never outlives its host. Also the keep-alive:
a host that goes silent (alive but stalled) stops the device within its
timeout. Real processes: these are the only tests here that spawn the CLI."""

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import hid_protocol as hp

from steadytouch.cli import main
from steadytouch.device import Device
from steadytouch.protocol import Ack, Telemetry
from steadytouch.record import CUT, read_recording
from steadytouch.transport import open_transport

from conftest import ROOT

EXE = str(Path(sys.executable).parent / "steadytouch")
AUTO = "auto=1000,1000,-1670,186000"


def children(pid: int) -> list[int]:
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def start(cmd, out: Path):
    p = subprocess.Popen([EXE, *cmd], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 30
    while time.time() < deadline and not (out.exists() and out.stat().st_size > 3000):
        time.sleep(0.1)
    assert out.exists(), p.communicate(timeout=5)
    kids = children(p.pid)
    assert kids, "the simulated device (the VM child) is not running"
    time.sleep(1.0)  # record for a while
    return p, kids


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_record_stops_cleanly_and_disarms_on_sigint_and_sigterm(tmp_path, sig):
    out = tmp_path / "rec.csv"
    p, kids = start(["record", str(out), "--device", f"sim://steady?{AUTO}"], out)
    p.send_signal(sig)
    stdout, stderr = p.communicate(timeout=20)
    assert p.returncode == 0, stderr
    assert "saved" in stdout and f"sim://steady?{AUTO}: disarmed" in stdout, stdout + stderr
    assert "Traceback" not in stderr
    assert not any(alive(k) for k in kids), "the simulated device outlived its host"
    meta, rows = read_recording(out)
    assert len(rows) >= 100 and CUT not in meta
    assert main(["audit", str(out)]) == 0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_monitor_disarms_on_sigint_and_sigterm(tmp_path, sig):
    p = subprocess.Popen([EXE, "monitor", "--device", f"sim://steady?{AUTO}"], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 30
    while time.time() < deadline and not children(p.pid):
        time.sleep(0.05)
    kids = children(p.pid)
    time.sleep(2.0)
    p.send_signal(sig)
    stdout, stderr = p.communicate(timeout=20)
    assert p.returncode == 0 and "Traceback" not in stderr, stderr
    assert "disarmed" in stdout.splitlines()[-1] and "0 stimulating" in stdout, stdout
    assert not any(alive(k) for k in kids)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc and PR_SET_PDEATHSIG")
@pytest.mark.parametrize("cmd", ["record", "monitor"])
def test_sigkill_of_the_host_takes_the_simulated_device_with_it(tmp_path, cmd):
    out = tmp_path / "rec.csv"
    argv = [cmd, str(out)] if cmd == "record" else [cmd]
    p = subprocess.Popen([EXE, *argv, "--device", f"sim://steady?{AUTO}"], cwd=ROOT, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL)
    deadline = time.time() + 30
    while time.time() < deadline and not (children(p.pid) and (cmd != "record" or (out.exists() and out.stat().st_size > 3000))):
        time.sleep(0.05)
    kids = children(p.pid)
    assert kids
    time.sleep(1.0)
    t_kill = time.monotonic()
    p.kill()
    p.wait()
    while any(alive(k) for k in kids) and time.monotonic() - t_kill < 10:
        time.sleep(0.005)
    gone_s = time.monotonic() - t_kill
    print(f"{cmd}: the simulated device was gone {gone_s * 1000:.0f} ms after SIGKILL of its host")
    assert not any(alive(k) for k in kids), "the simulated device outlived its host by 10 s"
    if cmd == "record":  # nothing recorded is lost but the last second; the cut is found and audited
        meta, rows = read_recording(out, allow_cut=True)
        assert len(rows) >= 50
        assert main(["audit", str(out)]) == 0


def test_a_silent_host_is_stopped_by_the_keepalive_within_its_timeout():
    """The host stays connected but stops talking (a stalled loop): the device stops every
    channel one keep-alive timeout after the host's last command (device clock)."""
    with open_transport(f"sim://steady?{AUTO}&channels=1") as t:
        d = Device(t)
        d.keep_alive(200)
        last = d.keepalive(200)  # the host's last word; its ack carries the device time
        time.sleep(1.0)  # silent: no read, no keep-alive
        reps = []
        while len(reps) < 500 and not any(isinstance(r, Telemetry) and r.stop == hp.STOP_KEEPALIVE for r in reps[:-5]):
            r = d.t.read(2.0)  # what the device sent meanwhile (the transport queues it), read without replying
            assert r is not None
            reps.append(d._decode(r))
        pulses = [r for r in reps if isinstance(r, Telemetry) and r.i_ua > 0 and r.time_us >= last.time_us]
        stops = [r for r in reps if isinstance(r, Telemetry) and r.stop == hp.STOP_KEEPALIVE]
        assert isinstance(last, Ack) and pulses and stops
        gap_ms = (pulses[-1].time_us - last.time_us) % (1 << 30) / 1000
        print(f"host silent -> last pulse after {gap_ms:.0f} ms (keep-alive 200 ms)")
        assert gap_ms <= 200  # checked before each frame's pulses: none starts later than the timeout
        assert all(not r.armed for r in stops)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc")
def test_a_second_ctrl_c_still_lets_the_disarm_out(tmp_path):
    """Two SIGINTs in quick succession: the DISARM is still sent before the CLI exits."""
    out = tmp_path / "rec.csv"
    p, kids = start(["record", str(out), "--device", f"sim://steady?{AUTO}"], out)
    p.send_signal(signal.SIGINT)
    time.sleep(0.002)
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=20)
    assert "Traceback" not in stderr and p.returncode in (0, 130), stderr
    assert f"sim://steady?{AUTO}: disarmed" in stdout, stdout + stderr
    assert not any(alive(k) for k in kids)
    assert read_recording(out, allow_cut=True)[1]
