"""`steadytouch flash` end to end on the emulated Pico (real MicroPython v1.28.0
for the RP2040 in rp2040js, served by host/emu: its USB serial and its HID
interface on two TCP ports, as one board on one cable): a blank board, the
firmware's boot and loop with its version read back over HID, Ctrl-C
maintenance without a watchdog reset, a re-flash onto the running board, a HID
interface that cannot be reached, a boot error kept in the board's log, and a
board in a watchdog reset loop (with the serial-REPL fallback). The tests run
in order on one board (about four minutes). Step timings:
bench/flash_emulated.py, docs/performance.md."""

import ast
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

import emu
from conftest import FIRMWARE, ROOT, tool
from steadytouch.flash import device_files

# what flash copies: every device file compiled, plus the two-line main.py stub beside st_main.mpy
N_FILES = len(device_files()) + 1

pytestmark = pytest.mark.skipif(not emu.available(), reason=emu.SKIP_REASON)

BOARD_LIB = emu.EMU / "board-lib"
EXE = str(Path(sys.executable).parent / "steadytouch")
FW = ".".join(str(v) for v in ast.literal_eval(
    re.search(r"^FW_VERSION = (\(.*\))$", (FIRMWARE / "stim.py").read_text(), re.M).group(1)))


@pytest.fixture(scope="module")
def pico(tmp_path_factory):
    log = tmp_path_factory.mktemp("emu") / "emu.log"
    with emu.Pico(log, seconds=900) as p:
        yield p


def flash(pico, build_dir, *extra, timeout=300, device=None, boot_timeout_s=120):
    """`steadytouch flash` onto the served board; its HID check reaches the same board (emu+tcp://)."""
    t0 = time.monotonic()
    dev = [] if "--no-hid-check" in extra else ["--device", device or pico.hid_url]
    p = subprocess.Popen([EXE, "flash", "--port", pico.url, *dev, "--lib-dir", str(BOARD_LIB), "--build-dir",
                          str(build_dir), "--boot-timeout-s", str(boot_timeout_s), *extra], cwd=ROOT, text=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    lines = []
    for line in p.stdout:
        lines.append((time.monotonic() - t0, line.rstrip("\n")))
    err = p.stderr.read()
    p.wait(timeout=timeout)
    return p.returncode, lines, err


def text(lines):
    return "\n".join(s for _, s in lines)


def mpremote(pico, *args, timeout=60, soft_reset=False):
    """`resume`: no soft reset, which would re-enumerate a running board's USB (docs/hardware.md)."""
    return subprocess.run([tool("mpremote"), "connect", pico.url, *([] if soft_reset else ["resume"]), *args],
                          capture_output=True, text=True, timeout=timeout)


def over_hid(pico, out):
    """Step 7 says the version came over HID from this board's HID interface, and the emulator saw it:
    a HID client on this board (after its last reset) that sent reports (GET_INFO) and was answered."""
    m = re.search(r"\[8/8\] boot check over HID \((\S+)\): steadytouch (\S+) on (\S+) answered GET_INFO, the version "
                  r"flashed; (\d+) telemetry reports", out)
    assert m, out
    assert m.group(1) == pico.hid_url and m.group(2) == FW and m.group(3) == "pico-stmisola" and int(m.group(4)) > 0
    t_end = time.monotonic() + 20  # the emulator logs the client's end a moment after flash closed it
    while "HID client disconnected after" not in pico.stderr().rsplit("hard reset", 1)[-1] and time.monotonic() < t_end:
        time.sleep(0.2)
    since_reset = pico.stderr().rsplit("hard reset", 1)[-1]
    assert "HID client connected (device 1209:0001)" in since_reset, since_reset[-1500:]
    counts = re.findall(r"HID client disconnected after (\d+) OUT and (\d+) IN reports", since_reset)
    assert any(int(o) >= 1 and int(i) >= 1 for o, i in counts), since_reset[-1500:]


def resets(pico, kind="watchdog timeout"):
    return pico.stderr().count(f"hard reset, {kind}")


def wait_until_running(pico, timeout_s=120):
    """The firmware re-enumerates USB (usb.device init) just before its loop starts: wait for
    that after the last reset, then a little for the first frames."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        log = pico.stderr()
        if "emulated host: enumerating again" in log.rsplit("hard reset", 1)[-1]:
            time.sleep(5)  # wall time for the loop's first frames, also with the suite's other worker busy
            return
        time.sleep(0.5)
    pytest.fail(f"the firmware did not start within {timeout_s} s:\n{pico.stderr()[-2000:]}")


def test_flash_a_blank_board_boots_and_runs_its_loop(pico, tmp_path):
    rc, lines, err = flash(pico, tmp_path / "dev")
    out = text(lines)
    assert rc == 0, out + err
    assert [s[:5] for _, s in lines if s.startswith("[")] == [f"[{k}/8]" for k in range(1, 9)]
    assert "no steadytouch loop was running" in out and "no error log on the board" in out
    assert "installed 3 files into /lib/usb/device" in out and f"copied {N_FILES} files, 0 unchanged" in out
    over_hid(pico, out)
    assert "serial REPL" not in out
    assert f"the board runs steadytouch firmware {FW}" in out
    assert resets(pico) == 0 and "Traceback" not in out


def test_ctrl_c_stops_stimulation_and_keeps_the_repl_without_a_watchdog_reset(pico):
    wait_until_running(pico)
    # mpremote's Ctrl-C and raw REPL, then 2 s of REPL work: 4x the watchdog's timeout
    p = mpremote(pico, "exec", "import time; time.sleep(2); print('alive')")
    assert p.returncode == 0 and "alive" in p.stdout, p.stdout + p.stderr
    # every output low: gate and amplitude pins are plain GPIO (FUNCSEL 5 = SIO) driven low, no PIO running
    probe = ("import machine, board_config as c\n"
             "pins = c.GATE_PINS + (c.DAC_SCK_PIN, c.DAC_MOSI_PIN)\n"
             "print([machine.mem32[0x40014004 + 8 * p] & 0x1F for p in pins], "
             "machine.mem32[0xD0000010] & sum(1 << p for p in pins), machine.mem32[0x50200000] & 0xF)")
    time.sleep(2)
    p = mpremote(pico, "exec", probe)
    assert p.returncode == 0, p.stderr
    funcsel, out_bits, sm_enabled = p.stdout.split("] ")[0] + "]", *p.stdout.split("] ")[1].split()
    assert set(ast.literal_eval(funcsel)) == {5} and int(out_bits) == 0 and int(sm_enabled) == 0, p.stdout
    # the loop's Ctrl-C check, on the chip: allocates nothing while no byte waits
    p = mpremote(pico, "exec", "import st_main, micropython\nc = st_main.CtrlC()\nwhile c.pressed():\n    pass\n"
                 "k = 0\nr = None\nmicropython.heap_lock()\nwhile k < 200:\n    r = c.pressed()\n    k += 1\n"
                 "micropython.heap_unlock()\nprint('no allocation', r)")
    assert p.stdout.strip() == "no allocation False", p.stdout + p.stderr
    assert resets(pico) == 0, pico.stderr()[-1500:]
    # a soft reset (mpremote's default) keeps the watchdog paused; the first one may lose the port while
    # the board's USB re-enumerates, so it is tried twice
    for _ in range(2):
        p = mpremote(pico, "exec", "import time; time.sleep(2); print('soft')", soft_reset=True)
        if p.returncode == 0:
            break
    assert "soft" in p.stdout, p.stderr
    assert resets(pico) == 0, pico.stderr()[-1500:]
    p = mpremote(pico, "reset")  # back to work
    assert p.returncode == 0, p.stderr


def test_flash_again_onto_the_running_board(pico, tmp_path):
    wait_until_running(pico)
    rc, lines, err = flash(pico, tmp_path / "dev")
    out = text(lines)
    assert rc == 0, out + err
    m = re.search(r"stopped steadytouch (\S+) \((\d+) frames\)", out)
    assert m and m.group(1) == FW and int(m.group(2)) > 0, out
    assert "all 3 files up to date" in out and f"copied 0 files, {N_FILES} unchanged" in out
    over_hid(pico, out)
    assert resets(pico) == 0


def test_a_stored_correction_the_new_firmware_would_ignore_stops_flash_before_it_copies(pico, tmp_path):
    """Issue 13 (deliverable 4): flash reads the board's /vmon_cal.txt over its REPL and judges it by the new
    firmware's rules before it changes anything. One stored under other windows (monitor gain 1.095) would
    be ignored at boot: one stderr line, nothing copied, the board reset to run what it ran."""
    wait_until_running(pico)
    p = mpremote(pico, "exec", "f = open('/vmon_cal.txt', 'w')\n"
                 "f.write('steadytouch monitor correction v1\\n0 1095000 0 0\\n')\nf.close()")
    assert p.returncode == 0, p.stderr
    try:
        rc, lines, err = flash(pico, tmp_path / "dev")
        out = text(lines)
        assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, out + err
        assert "stopped before copying anything: the board's stored correction /vmon_cal.txt would be ignored" in err
        assert "--ignore-stored-correction" in err and "correction file line 2: gain 1095000 ppm" in err
        assert "[5/8] stored correction /vmon_cal.txt: the new firmware would ignore it at boot" in out
        assert "[6/8]" not in out and "[7/8]" not in out
        wait_until_running(pico)  # reset by flash: the firmware it had runs again
    finally:
        mpremote(pico, "exec", "import os; os.remove('/vmon_cal.txt')")
        mpremote(pico, "reset")
    assert resets(pico) == 0


def test_a_hid_interface_that_cannot_be_reached_is_one_line_with_hints(pico, tmp_path):
    """The firmware runs but the HID device named is not there (a missing udev rule looks the same):
    flash waits --boot-timeout-s, asks the serial port why, and names what to check."""
    wait_until_running(pico)
    with socket.socket() as s:  # a port nobody serves
        s.bind(("127.0.0.1", 0))
        nobody = f"emu+tcp://127.0.0.1:{s.getsockname()[1]}"
    rc, lines, err = flash(pico, tmp_path / "dev", device=nobody, boot_timeout_s=25)
    assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, text(lines) + err
    assert re.search(r"the firmware runs \(\d+ frames, seen over the serial REPL on socket://", err), err
    assert f"its HID interface {nobody} cannot be reached within 25 s" in err
    assert "udev rule docs/70-steadytouch.rules" in err and "--no-hid-check" in err
    assert resets(pico) == 0


def test_a_boot_error_is_logged_without_a_reset_loop_and_flash_shows_and_mends_it(pico, tmp_path):
    wait_until_running(pico)
    p = mpremote(pico, "exec", "import os; os.remove('/lib/usb/device/core.mpy')")
    assert p.returncode == 0, p.stderr
    mpremote(pico, "reset")
    time.sleep(12)  # the boot fails at the USB set-up; it must stay down, not reset every 0.5 s
    assert resets(pico) == 0, pico.stderr()[-1500:]
    p = mpremote(pico, "exec", "print(open('/last_error.txt').read())")
    assert p.returncode == 0, p.stderr
    assert f"steadytouch {FW} stopped at boot; every output is off" in p.stdout
    assert "usb-device is not installed on the board: run `steadytouch flash`" in p.stdout
    assert "/work/" not in p.stdout and str(ROOT) not in p.stdout  # mpy-cross -s: no build-machine paths
    rc, lines, err = flash(pico, tmp_path / "dev")
    out = text(lines)
    assert rc == 0, out + err
    assert "[4/8] the board's error log /last_error.txt" in out and "usb-device is not installed" in out
    assert "installed 1 file into /lib/usb/device" in out
    over_hid(pico, out)
    p = mpremote(pico, "exec", "import os; print('/last_error.txt' in ['/' + n for n in os.listdir('/')])")
    assert p.stdout.strip() == "False"  # shown once, then cleared
    mpremote(pico, "reset")


BROKEN_MAIN = """import machine
machine.WDT(timeout=500)  # the old firmware: a watchdog started before a failing set-up
raise RuntimeError('broken main.py')
"""


def test_a_board_in_a_watchdog_reset_loop_is_recovered_by_flash(pico, tmp_path):
    wait_until_running(pico)
    broken = tmp_path / "main.py"
    broken.write_text(BROKEN_MAIN)
    p = mpremote(pico, "fs", "cp", str(broken), ":main.py")
    assert p.returncode == 0, p.stderr
    before = resets(pico)
    mpremote(pico, "reset")
    t_end = time.monotonic() + 60
    while resets(pico) < before + 3 and time.monotonic() < t_end:
        time.sleep(0.5)
    assert resets(pico) >= before + 3, "the broken main.py should reset the board again and again"
    rc, lines, err = flash(pico, tmp_path / "dev", "--no-hid-check")  # the serial-REPL fallback
    out = text(lines)
    assert rc == 0, out + err
    assert f"copied 1 file, {N_FILES - 1} unchanged" in out and f"the board runs steadytouch firmware {FW}" in out
    assert re.search(rf"\[8/8\] boot check: steadytouch {re.escape(FW)} ran [1-9]\d* frames with no error; version "
                     r"read back over the serial REPL, not over HID \(--no-hid-check\)", out), out
    n = resets(pico)
    time.sleep(5)
    assert resets(pico) == n  # the loop is over
