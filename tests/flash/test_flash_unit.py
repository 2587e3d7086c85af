"""`steadytouch flash` without a board: the build, the pinned libraries (lock,
fetch, refusal of unknown versions), each failure as one line, and the
firmware's boot-path pieces in the MicroPython VM."""

import functools
import http.server
import os
import pty
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from conftest import FIRMWARE, ROOT, SHARED, tool
from steadytouch import boardlib
from steadytouch import flash as F

BOARD_LIB = ROOT.parent / "shared" / "emulator" / "board-lib"
NEED_LIB = pytest.mark.skipif(not BOARD_LIB.is_dir(), reason=f"{BOARD_LIB} not found: the pinned usb-device copy "
                              "comes with ../shared/emulator beside the checkout")
EXE = str(Path(sys.executable).parent / "steadytouch")


def run(*args, env=None, timeout=120):
    e = dict(os.environ, **(env or {}))
    return subprocess.run([EXE, *args], capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=e)


def one_line_error(p, *words):
    assert p.returncode == 2, (p.stdout, p.stderr)
    assert "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
    for w in words:
        assert w in p.stderr, (w, p.stderr)


# ------------------------------------------------------------------ build
def test_build_has_no_build_machine_paths_and_a_stub_main(tmp_path):
    b = F.build(tmp_path / "dev")
    assert set(b.files) >= {"/main.py", "/st_main.mpy", "/stim.mpy", "/sensation_core.mpy", "/usb_hid64.mpy"}
    assert not any("board_sim" in k or "sim_electrode" in k for k in b.files)
    assert (tmp_path / "dev" / "main.py").read_text() == F.MAIN_STUB
    for name, p in b.files.items():
        data = p.read_bytes()
        assert str(ROOT).encode() not in data and b"/firmware/" not in data and b"/shared/" not in data, name
        if name.endswith(".mpy"):
            assert data[:2] == b"M\x06", name
    assert b"stim.py" in b.files["/stim.mpy"].read_bytes()  # the name tracebacks show
    assert b"main.py" in b.files["/st_main.mpy"].read_bytes()


@NEED_LIB
def test_build_compiles_the_pinned_libraries_as_mip_lays_them_out(tmp_path):
    libs = boardlib.check_folder(BOARD_LIB)
    b = F.build(tmp_path / "dev", libs)
    assert {k for k in b.files if k.startswith("/lib/")} == {
        "/lib/usb/device/__init__.mpy", "/lib/usb/device/core.mpy", "/lib/usb/device/hid.mpy"}
    assert b"usb/device/core.py" in b.files["/lib/usb/device/core.mpy"].read_bytes()


def test_a_compile_error_is_one_line_and_touches_no_board(tmp_path, monkeypatch):
    bad = tmp_path / "src" / "stim.py"
    bad.parent.mkdir()
    bad.write_text("def f(:\n    pass\n")
    monkeypatch.setattr(F, "device_files", lambda: [bad])
    with pytest.raises(F.FlashError, match=r"mpy-cross cannot compile .*stim.py: .*SyntaxError.*nothing was sent"):
        F.build(tmp_path / "dev")


# ------------------------------------------------------------------ pinned libraries
def test_the_lock_names_the_pinned_versions():
    assert boardlib.PACKAGES == (("usb-device", "0.2.1"), ("usb-device-hid", "0.1.2"))
    assert len(boardlib.COMMIT) == 40 and all(len(f.sha256) == 64 for f in boardlib.FILES)


@NEED_LIB
def test_the_shared_copy_matches_the_lock_and_a_changed_byte_is_refused(tmp_path):
    assert set(boardlib.check_folder(BOARD_LIB)) == {"usb/device/__init__.py", "usb/device/core.py",
                                                     "usb/device/hid.py", "LICENSE"}
    copy = tmp_path / "lib"
    shutil.copytree(BOARD_LIB, copy)
    hid = copy / "usb" / "device" / "hid.py"
    hid.write_text(hid.read_text().replace("interface_str=None,\n", "interface_str=None,\n        interval_ms=8,\n", 1))
    with pytest.raises(boardlib.LibError, match="hid.py is not the pinned .* refusing an unknown version"):
        boardlib.check_folder(copy)


@NEED_LIB
def test_online_fetch_fills_the_cache_and_checks_every_file(tmp_path, monkeypatch):
    """--online against a local server laid out like GitHub's raw files at the pinned commit."""
    site = tmp_path / "site" / boardlib.COMMIT
    for f in boardlib.FILES + (boardlib.LICENSE,):
        dst = site / f.upstream
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(BOARD_LIB / f.board, dst)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path / "site"))
    handler.log_message = lambda *a: None
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    url = f"http://127.0.0.1:{srv.server_address[1]}/{{commit}}/{{path}}"
    try:
        with pytest.raises(boardlib.LibError, match="not on this computer.*--online.*--lib-dir"):
            boardlib.locate(None, online=False, url=url)
        files, where = boardlib.locate(None, online=True, url=url)
        assert "downloaded from GitHub" in where and files["usb/device/hid.py"].read_bytes() == \
            (BOARD_LIB / "usb/device/hid.py").read_bytes()
        files, where = boardlib.locate(None, online=False, url=url)  # now offline, from the cache
        assert where.startswith("from the cache")
        shutil.rmtree(tmp_path / "cache")
        (site / boardlib.FILES[1].upstream).write_text("# not the pinned core.py\n")
        with pytest.raises(boardlib.LibError, match="does not match the pinned sha256.*refusing it"):
            boardlib.locate(None, online=True, url=url)
    finally:
        srv.shutdown()


def test_no_internet_names_the_offline_option(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    with pytest.raises(boardlib.LibError, match=r"cannot download .*without internet.*--lib-dir DIR"):
        boardlib.locate(None, online=True, url="http://127.0.0.1:9/{commit}/{path}")


# ------------------------------------------------------------------ the command line
def test_dry_run_lists_everything_and_stops_on_missing_libraries(tmp_path):
    env = {"XDG_CACHE_HOME": str(tmp_path / "cache")}
    p = run("flash", "--dry-run", "--build-dir", str(tmp_path / "dev"), env=env)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert "[1/8] compile" in p.stdout and "[2/8] libraries: missing" in p.stdout and "--online" in p.stdout
    assert ":/stim.mpy" in p.stdout and ":/main.py" in p.stdout and "board_sim" not in p.stdout
    assert "flash would stop there" in p.stderr
    p = run("flash", "--dry-run", "--online", "--build-dir", str(tmp_path / "dev"), env=env)
    assert p.returncode == 0 and "would download" in p.stdout and not (tmp_path / "cache").exists()


@NEED_LIB
def test_dry_run_with_the_libraries_lists_them(tmp_path):
    p = run("flash", "--dry-run", "--lib-dir", str(BOARD_LIB), "--build-dir", str(tmp_path / "dev"))
    assert p.returncode == 0, p.stderr
    assert ":/lib/usb/device/hid.mpy" in p.stdout and "sha256 checked" in p.stdout
    assert "dry run: nothing is copied, removed or written" in p.stdout
    assert "ask its HID interface hid://1209:0001 for the version (GET_INFO)" in p.stdout
    p = run("flash", "--dry-run", "--no-hid-check", "--lib-dir", str(BOARD_LIB), "--build-dir", str(tmp_path / "dev"))
    assert p.returncode == 0 and "read its version back over the serial REPL (--no-hid-check)" in p.stdout


@NEED_LIB
def test_no_board_is_one_line(tmp_path):
    p = run("flash", "--lib-dir", str(BOARD_LIB), "--port", "/dev/ttyNOSUCH0", "--build-dir", str(tmp_path / "d"))
    one_line_error(p, "no board at /dev/ttyNOSUCH0", "steadytouch devices")
    p = run("flash", "--lib-dir", str(BOARD_LIB), "--port", "socket://127.0.0.1:9", "--build-dir", str(tmp_path / "d"))
    one_line_error(p, "no board at socket://127.0.0.1:9")


@NEED_LIB
def test_a_busy_port_is_one_line(tmp_path):
    import serial

    master, slave = pty.openpty()
    name = os.ttyname(slave)
    holder = serial.Serial(name, exclusive=True)  # another program has the port
    try:
        p = run("flash", "--lib-dir", str(BOARD_LIB), "--port", name, "--build-dir", str(tmp_path / "d"))
        one_line_error(p, f"{name} is busy", "close it")
    finally:
        holder.close()
        os.close(master)
        os.close(slave)


@NEED_LIB
def test_a_port_without_micropython_is_one_line(tmp_path):
    master, slave = pty.openpty()  # answers nothing, like a board without MicroPython
    name = os.ttyname(slave)
    try:
        p = run("flash", "--lib-dir", str(BOARD_LIB), "--port", name, "--build-dir", str(tmp_path / "d"),
                timeout=200)
        one_line_error(p, f"the board at {name} does not answer with a MicroPython REPL", "Recover a board")
    finally:
        os.close(master)
        os.close(slave)


# ------------------------------------------------------------------ firmware pieces in the VM
FAKE_MACHINE = """
class _Mem:
    def __init__(self):
        self.d = {}
    def __getitem__(self, a):
        return self.d.get(a, 0)
    def __setitem__(self, a, v):
        self.d[a] = v
mem32 = _Mem()
"""

HID_PROBE = """
import usb_hid64
from usb.device.core import Descriptor
h = usb_hid64.Hid64()
strs = [None]
d = Descriptor(None)
h.desc_cfg(d, 0, 1, strs)
buf = bytearray(d.o)
h.desc_cfg(Descriptor(buf), 0, 1, strs)
print(len(buf), h._int_ep, h._out_ep, list(buf[-14:]))
"""


@NEED_LIB
def test_hid64_builds_its_descriptors_on_the_pinned_library(tmp_path, micropython):
    """The boot failure of issue 17 (`binterval`): Hid64 against the real usb-device-hid 0.1.2."""
    (tmp_path / "machine.py").write_text(FAKE_MACHINE)
    (tmp_path / "probe.py").write_text(HID_PROBE)
    env = dict(os.environ, MICROPYPATH=os.pathsep.join([str(tmp_path), str(BOARD_LIB), str(SHARED), str(FIRMWARE)]))
    p = subprocess.run([micropython, str(tmp_path / "probe.py")], capture_output=True, text=True, env=env, timeout=60)
    assert p.returncode == 0, p.stderr
    n, ep_in, ep_out, tail = p.stdout.split(" ", 3)
    assert (int(ep_in), int(ep_out)) == (0x81, 0x01)
    # two endpoint descriptors: 7 bytes each, 64-byte interrupt, bInterval 1 ms
    assert eval(tail) == [7, 5, 0x81, 3, 64, 0, 1, 7, 5, 0x01, 3, 64, 0, 1]


BOOT_PROBE = """
import sys
import main
import micropython
calls = []
ERR = OSError(19, 'no such device (a broken board in this test)' + 'x' * %(pad)d)
class FakeBoardRp2:
    def watchdog_pause(self):
        calls.append('pause')
    def outputs_off(self, cfg):
        calls.append('off')
    class Board:
        def __init__(self, cfg):
            micropython.heap_lock()
            micropython.heap_lock()  # as if the error landed in a heap-locked section
            raise ERR
    class Clock:
        pass
sys.modules['board_rp2'] = FakeBoardRp2()
main.ERROR_LOG = %(log)r
main.main_rp2()
x = [1, 2, 3]             # the heap is usable again
print(calls)
"""


@pytest.mark.parametrize("pad", [0, 5000])
def test_a_boot_error_is_printed_logged_capped_and_leaves_outputs_off(tmp_path, micropython, pad):
    log = tmp_path / "last_error.txt"
    (tmp_path / "probe.py").write_text(BOOT_PROBE % {"pad": pad, "log": str(log)})
    env = dict(os.environ, MICROPYPATH=os.pathsep.join([str(tmp_path), str(SHARED), str(FIRMWARE)]))
    p = subprocess.run([micropython, str(tmp_path / "probe.py")], capture_output=True, text=True, env=env, timeout=60)
    assert p.returncode == 0, p.stderr
    text = log.read_text()
    from steadytouch.flash import fw_version

    assert text.startswith(f"steadytouch {fw_version()} stopped at boot; every output is off")
    assert "OSError" in text and text in p.stdout
    assert len(text) <= 2048
    assert p.stdout.strip().endswith("['pause', 'pause', 'off']")


CTRL_C_PROBE = """
import sys, time, micropython
import main
class S:
    n = 0
    def run(self, k):
        self.n += k
        time.sleep_ms(1)
c = main.CtrlC()
assert c.pressed() is False        # nothing waiting (allocation: the unix port's poll allocates, the rp2's
print('ready')                     # does not: checked on the emulated Pico, test_flash_emulated.py)
s = S()
main.run_until_ctrl_c(s, c)
rest = sys.stdin.buffer.read(2)    # what follows Ctrl-C stays for the REPL (mpremote's Ctrl-A)
print('stopped', s.n > 0, rest)
"""


def test_ctrl_c_is_read_between_frames(tmp_path, micropython):
    (tmp_path / "probe.py").write_text(CTRL_C_PROBE)
    env = dict(os.environ, MICROPYPATH=os.pathsep.join([str(SHARED), str(FIRMWARE)]))
    p = subprocess.Popen([micropython, str(tmp_path / "probe.py")], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, env=env)
    assert p.stdout.readline() == b"ready\n"
    p.stdin.write(b"ab\r\x03\r\x01")  # mpremote: Ctrl-C, then Ctrl-A for the raw REPL
    p.stdin.flush()
    out, err = p.communicate(timeout=60)
    assert p.returncode == 0, err
    assert out.decode().strip() == "stopped True b'\\r\\x01'"
