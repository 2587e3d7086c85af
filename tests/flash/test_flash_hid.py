"""`steadytouch flash`'s last step without a board: the version read back over HID
(GET_INFO answered by the real firmware in the MicroPython VM through sim://, the
serial link faked), the diagnosis when the HID interface does not appear, the
fallback's reason, and the emu+tcp:// transport against a local line server."""

import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from conftest import ROOT
from steadytouch import flash as F
from steadytouch import transport as T

EXE = str(Path(sys.executable).parent / "steadytouch")


class FakeLink:
    def __init__(self, log):
        self.log = log

    def reset(self):
        self.log.append("reset")

    def close(self):
        pass


def fake_serial(monkeypatch, state=None, fail=None):
    """F.connect without a board: records each connect and reset; returns `state` or raises `fail`."""
    log = []

    def connect(port, timeout_s, tries=3):
        log.append("connect")
        if fail and log.count("connect") > 1:
            raise F.FlashError(fail)
        return FakeLink(log), state

    monkeypatch.setattr(F, "connect", connect)
    return log


def state(**kw):
    base = dict(platform="rp2", version=(1, 28, 0), machine="Raspberry Pi Pico with RP2040", mpy=6, log=None)
    return F.BoardState(**dict(base, **kw))


def unused_url():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"emu+tcp://127.0.0.1:{s.getsockname()[1]}"


# ------------------------------------------------------------------ the HID check
def test_the_version_comes_back_over_hid_from_the_running_firmware(monkeypatch):
    """sim:// is the real firmware answering over the same report stream as hid://."""
    calls = fake_serial(monkeypatch)
    said = []
    info = F.boot_check_hid("PORT", "sim://steady", F.fw_version(), 60, said.append)
    assert calls == ["connect", "reset"]  # reset once; the board keeps running afterwards
    assert info.firmware == F.fw_version() and info.board == "pico-stmisola"
    assert said[0].startswith(f"[8/8] boot check over HID (sim://steady): steadytouch {F.fw_version()} on "
                              "pico-stmisola answered GET_INFO, the version flashed; ")
    n = int(said[0].split("; ")[1].split()[0])
    assert n > 0 and "no firmware error" in said[0]


def test_a_different_version_over_hid_is_refused(monkeypatch):
    fake_serial(monkeypatch)
    with pytest.raises(F.FlashError, match=r"answers with steadytouch firmware \d+\.\d+\.\d+, but 9\.9\.9 was just "
                                           r"flashed onto PORT: is another steadytouch board plugged in"):
        F.boot_check_hid("PORT", "sim://steady", "9.9.9", 60, print)


def test_no_hid_and_a_boot_error_shows_the_boards_log(monkeypatch):
    calls = fake_serial(monkeypatch, state(log="steadytouch 0.1.0 stopped at boot; every output is off\n"
                                              "ImportError: no module named 'usb.device'\n"))
    said = []
    with pytest.raises(F.FlashError, match=r"the firmware did not boot \(its log is /last_error.txt"):
        F.boot_check_hid("PORT", unused_url(), "0.1.0", 1.0, said.append)
    assert said[0] == "the firmware failed at boot:" and "ImportError" in said[2]
    assert calls == ["connect", "reset", "connect", "reset"]  # looked over serial, then let it boot again


def test_no_hid_while_the_firmware_runs_names_the_udev_rule(monkeypatch):
    fake_serial(monkeypatch, state(fw=(0, 1, 0), frames=250, errors=0))
    url = unused_url()
    with pytest.raises(F.FlashError) as e:
        F.boot_check_hid("PORT", url, "0.1.0", 1.0, print)
    msg = str(e.value)
    assert "the firmware runs (250 frames, seen over the serial REPL on PORT)" in msg
    assert f"its HID interface {url} cannot be reached within 1 s: no emulated Pico served at {url}" in msg
    assert "udev rule docs/70-steadytouch.rules" in msg and "--no-hid-check" in msg and "\n" not in msg


def test_no_hid_and_no_serial_names_the_cable(monkeypatch):
    fake_serial(monkeypatch, state(), fail="no board at PORT (could not open port)")
    with pytest.raises(F.FlashError, match=r"came back neither over HID .* nor on PORT within 1 s .*check the USB "
                                           r"cable \(a data cable"):
        F.boot_check_hid("PORT", unused_url(), "0.1.0", 1.0, print)


def test_no_hid_no_loop_no_log_says_how_to_look(monkeypatch):
    fake_serial(monkeypatch, state())
    with pytest.raises(F.FlashError, match=r"did not start within 1 s of its reset .*mpremote connect PORT repl.*"
                                           r"--boot-timeout-s"):
        F.boot_check_hid("PORT", unused_url(), "0.1.0", 1.0, print)


def test_the_fallback_is_taken_only_without_a_hid_backend(monkeypatch):
    assert F.hid_unavailable("hid://1209:0001") is None  # hidapi is installed here
    assert F.hid_unavailable("emu+tcp://127.0.0.1:1") is None

    def no_hidapi():
        raise ImportError("No module named 'hid'")

    monkeypatch.setattr(T, "_hid_module", no_hidapi)
    why = F.hid_unavailable("hid://1209:0001")
    assert why.startswith("no HID backend on this computer (No module named 'hid'") and "make setup" in why


def test_a_running_steadytouch_board_is_found_by_its_own_ids(monkeypatch):
    from serial.tools import list_ports

    class P:
        def __init__(self, device, vid, pid):
            self.device, self.vid, self.pid = device, vid, pid

    monkeypatch.setattr(list_ports, "comports", lambda: [P("/dev/ttyUSB0", 0x0403, 0x6001),
                                                         P("/dev/ttyACM3", 0x1209, 0x0001)])
    assert F.find_port() == "/dev/ttyACM3"
    monkeypatch.setattr(list_ports, "comports", lambda: [P("/dev/ttyACM0", 0x2E8A, 0x0005)])
    assert F.find_port() == "/dev/ttyACM0"
    monkeypatch.setattr(list_ports, "comports", lambda: [P("/dev/ttyACM0", 0x1209, 0x0002)])
    with pytest.raises(F.FlashError, match="no Raspberry Pi Pico found"):
        F.find_port()


# ------------------------------------------------------------------ emu+tcp://
class LineServer:
    """A stand-in for host/emu's HID port: a greeting, then each OUT line answered by `reply(line)`."""

    def __init__(self, greeting, reply=lambda line: None):
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.url = f"emu+tcp://127.0.0.1:{self.srv.getsockname()[1]}"
        self.got = []
        self.greeting, self.reply = greeting, reply
        threading.Thread(target=self.serve, daemon=True).start()

    def serve(self):
        while True:
            try:
                c, _ = self.srv.accept()
            except OSError:
                return
            with c, c.makefile("rwb") as f:  # both closed: the client sees the end
                f.write(self.greeting)
                f.flush()
                for line in f:
                    self.got.append(line.strip())
                    r = self.reply(line.strip())
                    if r is None:
                        break
                    f.write(r)
                    f.flush()

    def close(self):
        self.srv.close()


def test_emu_tcp_moves_whole_reports_both_ways():
    srv = LineServer(b"HID 1209:0001\n", reply=lambda line: bytes(reversed(bytes.fromhex(line.decode()))).hex()
                     .encode() + b"\n")
    try:
        with T.open_transport(srv.url) as t:
            assert t.ids == (0x1209, 0x0001)
            t.write(bytes(range(64)))
            assert t.read(5) == bytes(reversed(range(64)))
            assert srv.got == [bytes(range(64)).hex().encode()]
            assert t.read(0.05) is None
    finally:
        srv.close()


def test_emu_tcp_a_board_without_hid_is_no_device_and_a_reset_is_disconnected():
    srv = LineServer(b"NOHID the board has no HID interface (yet)\n")
    try:
        with pytest.raises(T.TransportError, match=r"no HID device at emu\+tcp://127.0.0.1:\d+: the board has no HID"):
            T.open_transport(srv.url)
    finally:
        srv.close()
    srv = LineServer(b"HID 1209:0001\n", reply=lambda line: None)  # the board resets at the first report
    try:
        with T.open_transport(srv.url) as t:
            t.write(bytes(64))
            with pytest.raises(T.Disconnected, match="went away"):
                while True:
                    t.read(2)
    finally:
        srv.close()
    srv = LineServer(b"SSH-2.0-OpenSSH\n")
    try:
        with pytest.raises(T.TransportError, match="is not an emulated Pico's HID port"):
            T.open_transport(srv.url)
    finally:
        srv.close()


@pytest.mark.parametrize("url", ["emu+tcp://127.0.0.1", "emu+tcp://127.0.0.1:0", "emu+tcp://127.0.0.1:70000",
                                 "emu+tcp://127.0.0.1:x", "emu+tcp://127.0.0.1:5/more"])
def test_emu_tcp_bad_urls_are_one_line(url):
    p = subprocess.run([EXE, "info", "--device", url], capture_output=True, text=True, timeout=60, cwd=ROOT,
                       env=dict(os.environ))
    assert p.returncode == 2 and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "emu+tcp://HOST:PORT with PORT in [1, 65535]" in p.stderr


def test_emu_tcp_nothing_served_is_one_line():
    url = unused_url()
    p = subprocess.run([EXE, "info", "--device", url], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert f"no emulated Pico served at {url}" in p.stderr and "python -m steadytouch.emu serve" in p.stderr


# ------------------------------------------------------------------ python -m steadytouch.emu serve
def test_serve_without_the_emulator_is_one_line(tmp_path):
    p = subprocess.run([sys.executable, "-m", "steadytouch.emu", "serve"], capture_output=True, text=True,
                       timeout=60, env=dict(os.environ, CHIP_EMULATOR=str(tmp_path)))
    assert p.returncode == 2 and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "build-firmware.sh" in p.stderr


def test_serve_prints_both_urls_and_a_blank_board_has_no_hid_device(tmp_path):
    import signal

    import emu

    if not emu.available():
        pytest.skip(emu.SKIP_REASON)
    p = subprocess.Popen([sys.executable, "-m", "steadytouch.emu", "serve", "--seconds", "120", "--log",
                          str(tmp_path / "emu.log")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        serial_url = p.stdout.readline().split()[-1]
        hid_url = p.stdout.readline().split()[-1]
        assert serial_url.startswith("socket://127.0.0.1:") and hid_url.startswith("emu+tcp://127.0.0.1:")
        # stock MicroPython has no HID interface: like hid:// with no board, one line
        q = subprocess.run([EXE, "info", "--device", hid_url], capture_output=True, text=True, timeout=60, cwd=ROOT)
        assert q.returncode == 2 and len(q.stderr.strip().splitlines()) == 1, q.stderr
        assert f"no HID device at {hid_url}: the board has no HID interface (yet)" in q.stderr
    finally:
        p.send_signal(signal.SIGINT)
        p.wait(timeout=30)
    assert p.returncode == 0 and "Traceback" not in p.stderr, p.stderr


def test_a_stored_correction_the_new_firmware_ignores_is_one_warning_line(monkeypatch, tmp_path):
    """Review of d560dd3 (finding 2b): a correction file stored under the old, wider windows is
    ignored by the firmware just flashed (every channel uncorrected); the boot check reads GET_INFO
    anyway, so it says so in one line (the flash itself succeeds); the serial fallback too."""
    import hid_protocol as hp

    monkeypatch.setenv("STEADYTOUCH_SIM_FLASH", str(tmp_path))
    said = []
    for text, warned in (("steadytouch monitor correction v1\n0 1095000 0 0\n", True),
                         ("steadytouch monitor correction v1\n0 1010000 0 0\n", False)):
        (tmp_path / "vmon_cal.txt").write_text(text)
        fake_serial(monkeypatch)
        said.clear()
        F.boot_check_hid("PORT", "sim://steady", F.fw_version(), 60, said.append)
        lines = [s for s in said if "ignored its stored correction" in s]
        assert len(lines) == (1 if warned else 0), said
        assert all("`steadytouch selftest` again" in s for s in lines)
    said.clear()
    fake_serial(monkeypatch, state(fw=(0, 1, 0), frames=50, errors=0, vmon=hp.VMON_BAD))
    monkeypatch.setattr(F.time, "sleep", lambda s: None)
    F.boot_check("PORT", 5, said.append, None)
    assert [s for s in said if "ignored its stored correction" in s], said
