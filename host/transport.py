"""Transports: one interface, chosen by a URL-like device name (in the spirit of
pyserial's `loop://` handlers).

- `hid://VID:PID[/SERIAL]` — the board over USB HID, through hidapi
  (hidraw backend on Linux when available). Default: `hid://1209:0001`.
- `sim://SCENARIO[?channels=N&seed=S&realtime=0|1&auto=I0,T0,X,Y&mode=akhtar|open&board=ideal&load=OHMS]`
  — the real firmware in the MicroPython VM with the simulated board, speaking
  the same report stream on its stdio. The board has the real parts' analog
  errors unless `board=ideal`; `load=OHMS` puts a resistor in place of the
  electrodes (the self-test's dummy load). In real time its scenario (and its
  `frames`, by default the scenario's length) starts with the host's session
  (`begin()`: record, monitor, arm), not at the VM's boot.
- `emu://[SCENARIO][?channels=N&seed=S&auto=I0,T0,X,Y&load=OHM&board=real|ideal]` — the real MicroPython rp2
  firmware on the emulated Pico (rp2040js, ../shared/emulator): its main loop
  (main_rp2) over its USB HID interface, the simulated electrode on its ADC.
- `emu+tcp://127.0.0.1:PORT` — the HID interface of an emulated Pico that is
  already running and served on TCP (`python -m steadytouch.emu serve`, or
  host/emu's `serve`, beside its USB serial for mpremote and `steadytouch
  flash --port socket://...`): attaches to that board as hid:// attaches to a
  plugged-in one, without booting anything.

Every transport moves whole 64-byte reports: `read(timeout_s)` returns one IN
report or None on timeout, `write(report)` sends one OUT report. Decoding, gap
detection and commands live above, in `device.py`, the same for all.
"""

from __future__ import annotations

import queue
import subprocess
import sys
import threading
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import hid_protocol as hp

DEFAULT_URL = f"hid://{hp.VID:04x}:{hp.PID:04x}"
UDEV_RULE = "docs/70-steadytouch.rules"


class TransportError(Exception):
    """A device problem the user can fix; the message says how."""


class Disconnected(TransportError):
    pass


class Transport:
    url = ""
    # False for a simulated device on its virtual clock (keep-alive off there: its
    # time runs far faster than a host can answer); Device.live() then sends none
    realtime = True
    # how long a command may wait for its answer (wall clock); Device.command's default
    answer_s = 2.0

    def read(self, timeout_s: float) -> bytes | None:
        raise NotImplementedError

    def write(self, report: bytes) -> None:
        raise NotImplementedError

    def begin(self) -> None:
        """The host's session begins (Device.live: record, monitor, arm). A board has nothing
        to start; sim:// starts its scenario's clock here."""

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _hid_module():
    if sys.platform.startswith("linux"):
        try:
            import hidraw  # cython-hidapi's hidraw backend

            return hidraw
        except ImportError:
            pass
    import hid

    return hid


class HidTransport(Transport):
    def __init__(self, vid: int, pid: int, serial: str | None = None, hid_module=None):
        self.url = f"hid://{vid:04x}:{pid:04x}" + (f"/{serial}" if serial else "")
        mod = hid_module or _hid_module()
        found = [d for d in mod.enumerate(vid, pid) if not serial or d.get("serial_number") == serial]
        if not found:
            raise TransportError(
                f"no device at {self.url}: is the board plugged in and flashed (`steadytouch flash`)? "
                "`steadytouch devices` lists what is connected; `sim://peel` runs the simulator instead")
        self.dev = mod.device()
        try:
            self.dev.open(vid, pid, serial) if serial else self.dev.open(vid, pid)
        except OSError as e:
            raise TransportError(
                f"cannot open {self.url} ({e}): permission denied? Install the udev rule {UDEV_RULE} "
                "(see docs/hardware.md) and re-plug the board") from None

    def read(self, timeout_s: float) -> bytes | None:
        try:
            data = self.dev.read(hp.REPORT_LEN, max(1, int(timeout_s * 1000)))
        except (OSError, ValueError) as e:
            raise Disconnected(f"{self.url} went away ({e})") from None
        if not data:
            return None
        if len(data) != hp.REPORT_LEN:
            raise Disconnected(f"{self.url} sent a {len(data)}-byte report; expected {hp.REPORT_LEN}")
        return bytes(data)

    def write(self, report: bytes) -> None:
        try:
            n = self.dev.write(b"\x00" + bytes(report))  # report ID 0: no IDs in our descriptor
        except (OSError, ValueError) as e:
            raise Disconnected(f"{self.url} went away ({e})") from None
        if n is not None and n < 0:
            raise Disconnected(f"{self.url}: write failed")

    def close(self) -> None:
        try:
            self.dev.close()
        except Exception:
            pass


class SimTransport(Transport):
    """The firmware in the MicroPython VM; reports over its stdin/stdout."""

    def __init__(self, scenario: str, channels: int = 2, seed: int = 1, realtime: bool = True,
                 auto: str | None = None, mode: str = "akhtar", frames: int | None = None,
                 ideal: bool = False, load_ohm: int = 0):
        from .simrun import FIRMWARE, board_args, firmware_module, micropython_exe, vm_popen

        self.url = f"sim://{scenario}"
        self.realtime = realtime
        args = [micropython_exe(), str(FIRMWARE / "main.py"), "--scenario", scenario, "--channels", str(channels),
                "--seed", str(seed), "--mode", mode, "--exit-on-eof"] + board_args(ideal, load_ohm)
        if realtime:
            # the board's keep-alive, on the host's time line; the scenario and its frames wait for
            # begin(): however long the host waits before its session (an LSL recorder), the
            # session gets the whole scenario, and the device does not run out before it starts
            args += ["--realtime", "--hold"]
        else:
            args += ["--keepalive-ms", "0"]  # virtual time outruns any host: off (docs/safety.md)
        if auto:
            args += ["--auto", auto]
        if frames:
            args += ["--frames", str(frames)]
        self.p = vm_popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=0)
        self.q: queue.Queue = queue.Queue(maxsize=100000)
        self.error = ""
        bs = firmware_module("board_sim")  # the simulated world's message that starts the scenario
        self._start = bytes((bs.MAGIC0, bs.MAGIC_SIM, bs.SIM_START)) + bytes(hp.REPORT_LEN - 1) if realtime else None
        self.reader = threading.Thread(target=self._pump, daemon=True)
        self.reader.start()

    def _pump(self):
        buf = b""
        out = self.p.stdout
        while True:
            chunk = out.read1(65536) if hasattr(out, "read1") else out.read(4096)
            if not chunk:
                break
            buf += chunk
            while len(buf) >= 66:
                if buf[0] == 0xA5 and buf[1] == 0x5A:
                    self.q.put(buf[2:66])
                    buf = buf[66:]
                else:
                    buf = buf[1:]
        self.p.wait()
        err = self.p.stderr.read().decode(errors="replace").strip()
        self.error = err.splitlines()[0] if err else ""
        self.q.put(None)  # end of stream

    def read(self, timeout_s: float) -> bytes | None:
        try:
            r = self.q.get(timeout=timeout_s)
        except queue.Empty:
            return None
        if r is None:
            self.q.put(None)
            raise Disconnected(self._stopped())
        return r

    def _stopped(self) -> str:
        """Why the simulated device is gone: its exit code and its first stderr line, whichever of a read
        or a write noticed first (the reader thread has then seen the process end: it waited for it)."""
        self.reader.join(timeout=5)  # the pump ends right after the process: its exit code and stderr
        rc = self.p.poll()
        if rc is None:
            return "the simulated device closed its input" + (f": {self.error}" if self.error else "")
        msg = f"the simulated device stopped (exit code {rc})"
        if rc == 0 and not self.error:
            msg += ": it ran its frames (the scenario's length from the session's start, or frames=N of the URL)"
        return msg + (f": {self.error}" if self.error else "")

    def write(self, report: bytes) -> None:
        self._send(b"\xa5\x5a" + bytes(report))

    def begin(self) -> None:
        """Start the scenario (once): a message to the simulated world, not a report (board_sim)."""
        if self._start is not None:
            start, self._start = self._start, None
            self._send(start)

    def _send(self, frame: bytes) -> None:
        try:
            self.p.stdin.write(frame)
            self.p.stdin.flush()
        except (BrokenPipeError, OSError):  # it exited between two reads: say why, as a read would
            raise Disconnected(self._stopped()) from None

    def close(self) -> None:
        try:
            self.p.stdin.close()  # --exit-on-eof: the simulated device stops and exits
        except OSError:
            pass
        if self.p.poll() is None:
            try:
                self.p.wait(timeout=0.5)
                return
            except subprocess.TimeoutExpired:
                pass
            self.p.terminate()
            try:
                self.p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.p.kill()


class EmuTransport(Transport):
    """The real rp2 firmware on the emulated Pico (host/emu): the Node host boots it from
    a flash image holding the project's device files in /lib, runs `import main` (the
    board's main_rp2 loop, as at power-up) and streams HID reports, one hex line each
    way, while the electrodes of a sim_electrode scenario feed the ADC (the simulator's
    model ported to JS, host/emu/host.mjs). Emulated time never runs ahead of wall
    time, so the device's keep-alive (emulated clock) is safe against the host's (wall
    clock). Each open boots a fresh chip: nothing the board was told carries over to
    the next command (`auto=` calibrates and sets the paper's mode at open)."""

    BOOT_S = 120  # first use: npm ci, compile, flash image; then a few seconds
    # the emulated chip can fall behind wall time on a loaded machine (never ahead of it)
    answer_s = 10.0

    def __init__(self, scenario: str = "steady", channels: int = 2, seed: int = 1,
                 auto: tuple[int, int, int, int] | None = None, load_ohm: int = 0, ideal: bool = False):
        import shutil
        import tempfile

        from . import emu
        from .simrun import firmware_module

        self.url = (f"emu://{scenario}?channels={channels}&seed={seed}" + (f"&load={load_ohm}" if load_ohm else "")
                    + f"&board={'ideal' if ideal else 'real'}")
        self.host = None
        self._pushed = None
        mpy_dir = Path(tempfile.mkdtemp(prefix="steadytouch-emu-"))
        try:
            if not shutil.which("node"):
                raise TransportError("emu:// needs Node >= 20 (`node` on the PATH) to run the emulated Pico")
            emu.check_emulator()
            host = emu.start_host(emu.mpy_cross(), mpy_dir=mpy_dir, die_with_parent=True)
        except emu.NoEmulator:
            raise TransportError(f"emu:// needs the emulated Pico in {emu.EMULATOR} (../shared/emulator beside the "
                                 "checkout: MicroPython's firmware.uf2, the boot ROM and rp2run.mjs; rebuild it with "
                                 "its build-firmware.sh, see docs/hardware.md; CHIP_EMULATOR=DIR points elsewhere)") \
                from None
        except emu.ChipUnavailable as e:
            raise TransportError(f"emu://: {e}") from None
        finally:
            shutil.rmtree(mpy_dir, ignore_errors=True)
        self.host = host
        try:
            sim_electrode = firmware_module("sim_electrode")
            scen = sim_electrode.scenario(scenario)
            e = sim_electrode.Electrode()
            chip = host.boot(host.image)
            chip.wiring(emu.load_cfg(), channels)
            code = f"import board_config\nboard_config.N_CHANNELS = {channels}\nimport main\n"
            spec = {"keys": [list(k) for k in scen.keys], "interp_h": scen.interp_h, "seed": seed, "noise_counts": 1.5,
                    "electrode": {k: getattr(e, k) for k in ("area0", "rs", "rho_ref", "j_ref", "beta", "c", "alpha")}}
            if load_ohm:  # a resistor on every channel instead of the electrodes (the self-test's dummy load)
                spec["load_ohm"] = load_ohm
            if not ideal:  # the realistic board: the simulator's analog errors, from board_sim itself
                bs = firmware_module("board_sim")
                cfg = emu.load_cfg()
                spec["noise_counts"] = bs.ADC_NOISE_COUNTS
                spec["analog"] = {
                    "dac_gain": [bs.DAC_GAIN[k % 4] for k in range(channels)],
                    "mon_gain": [bs.MON_GAIN[k % 4] for k in range(channels)],
                    "mon_off_counts": [bs.MON_OFFSET_MV[k % 4] * 1000.0 / cfg.VMON_UV_PER_COUNT
                                       for k in range(channels)],
                    "dnl_codes": list(bs.ADC_DNL_CODES), "dnl_width": bs.ADC_DNL_WIDTH}
            host.call("stream", code=code, scenario=spec)
        except emu.ChipError as err:
            self.close()
            raise TransportError(f"emu://: the emulated Pico did not start: {str(err).splitlines()[0]}") from None
        except BaseException:
            self.close()
            raise
        self._ready(auto)

    def _ready(self, auto) -> None:
        """Wait for the board's main loop (its first answer, over HID like any host command),
        so a caller's first command is not sent into a chip still booting; then `auto=`:
        the paper's mode and a calibration."""
        import sensation_core as sc

        from .device import Device, DeviceError

        d = Device(self)
        try:
            d.command(d.cmds.get_info(), timeout_s=self.BOOT_S)
        except DeviceError:
            self.close()
            raise TransportError(f"emu://: the emulated Pico's main loop did not answer within {self.BOOT_S} s "
                                 "(see .cache/chip/host.log)") from None
        if not auto:
            return
        try:
            d.command(d.cmds.set_mode(sc.MODE_AKHTAR))
            d.calibrate(*auto, hp.CH_ALL)
        except DeviceError as e:
            self.close()
            raise TransportError(f"emu://: auto={','.join(map(str, auto))} refused: {e}") from None

    def _lost(self) -> Disconnected:
        self.host.p.wait(timeout=5) if self.host.p.poll() is None else None
        self.host.err_thread.join(timeout=2)
        why = self.host.last_err.removeprefix("[emu] ")
        return Disconnected(f"the emulated Pico stopped (exit code {self.host.p.returncode})"
                            + (f": {why}" if why else ""))

    def read(self, timeout_s: float) -> bytes | None:
        import queue as _q

        try:
            line = self.host.lines.get(timeout=timeout_s)
        except _q.Empty:
            return None
        if not line:
            self.host.lines.put(b"")
            raise self._lost()
        try:
            r = bytes.fromhex(line.decode().strip())
        except ValueError:
            raise Disconnected(f"the emulated Pico sent a line that is not a report: {line[:60]!r}") from None
        if len(r) != hp.REPORT_LEN:
            raise Disconnected(f"the emulated Pico sent a {len(r)}-byte report; expected {hp.REPORT_LEN}")
        return r

    def write(self, report: bytes) -> None:
        try:
            self.host.p.stdin.write(bytes(report).hex().encode() + b"\n")
            self.host.p.stdin.flush()
        except (BrokenPipeError, OSError, ValueError):
            raise self._lost() from None

    def close(self) -> None:
        if self.host is not None:
            self.host.close()  # stdin EOF: the Node host exits, the emulated board with it


class EmuTcpTransport(Transport):
    """The HID interface of a running emulated Pico served on TCP (host/emu/host.mjs's
    `serve`): one greeting line (`HID VVVV:PPPP`, or `NOHID why` when the board has no
    HID interface enumerated: then there is no device, as hid:// finds none), then one
    64-byte report in hex a line each way. The board falls behind wall time on a busy
    machine, so a command may wait longer for its answer (answer_s)."""

    answer_s = 10.0
    CONNECT_S = 5.0

    def __init__(self, host: str, port: int):
        import socket

        self.url = f"emu+tcp://{host}:{port}"
        self.q: queue.Queue = queue.Queue()
        self.why = ""
        try:
            self.sock = socket.create_connection((host, port), timeout=self.CONNECT_S)
        except OSError as e:
            raise TransportError(f"no emulated Pico served at {self.url} ({e.strerror or e}): start one with "
                                 "`python -m steadytouch.emu serve`") from None
        try:
            self.rfile = self.sock.makefile("rb")
            greeting = self.rfile.readline(200).decode("ascii", "replace").strip()
        except OSError as e:
            self.close()
            raise TransportError(f"the emulated Pico at {self.url} did not greet ({e})") from None
        word, _, rest = greeting.partition(" ")
        if word != "HID":
            self.close()
            if word == "NOHID":
                raise TransportError(f"no HID device at {self.url}: {rest or 'the board has no HID interface'}")
            raise TransportError(f"{self.url} is not an emulated Pico's HID port (it said {greeting[:60]!r})")
        try:
            vid_s, pid_s = rest.split()[0].split(":")
            self.ids = (int(vid_s, 16), int(pid_s, 16))
        except (IndexError, ValueError):
            self.ids = None  # the board did not answer GET_DESCRIPTOR(device) in time
        self.sock.settimeout(None)
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self):
        try:
            for line in self.rfile:
                try:
                    r = bytes.fromhex(line.decode("ascii").strip())
                except ValueError:
                    self.why = f"a line that is not a report: {line[:60]!r}"
                    break
                if len(r) != hp.REPORT_LEN:
                    self.why = f"a {len(r)}-byte report; expected {hp.REPORT_LEN}"
                    break
                self.q.put(r)
        except (OSError, ValueError):
            pass
        self.q.put(None)

    def read(self, timeout_s: float) -> bytes | None:
        try:
            r = self.q.get(timeout=timeout_s)
        except queue.Empty:
            return None
        if r is None:
            self.q.put(None)
            raise Disconnected(f"{self.url} went away ({self.why or 'the board reset or left the USB bus'})")
        return r

    def write(self, report: bytes) -> None:
        try:
            self.sock.sendall(bytes(report).hex().encode() + b"\n")
        except OSError as e:
            raise Disconnected(f"{self.url} went away ({e})") from None

    def close(self) -> None:
        try:
            self.sock.close()
        except (OSError, AttributeError):
            pass


# the options each simulated device URL takes, and their values (for the error naming them)
SIM_OPTIONS = {"channels": "1-4", "seed": "a whole number", "frames": "a whole number of frames, then it stops",
               "realtime": "1|0 (also yes|no, true|false)", "auto": "I0_UA,T0_US,XSTAR_OHM,YSTAR_PC",
               "mode": "akhtar|fast|open|charge|energy|pwlinear", "board": "real|ideal", "load": "100-1000000 ohm"}
EMU_OPTIONS = {"scenario": "a scenario name or .csv file", "channels": "1-4", "seed": "a whole number",
               "auto": "I0_UA,T0_US,XSTAR_OHM,YSTAR_PC", "board": "real|ideal", "load": "100-1000000 ohm"}
_YES, _NO = ("1", "yes", "true"), ("0", "no", "false")


def _known_options(url: str, query: str, accepted: dict[str, str]):
    """The query's options (parse_qs), or TransportError naming an option the URL does not take (a typo such as
    chanels=4 was silently ignored) with every accepted option and its values."""
    q = parse_qs(query, keep_blank_values=True)
    unknown = [k for k in q if k not in accepted]
    if unknown:
        opts = "; ".join(f"{k}={v}" for k, v in accepted.items())
        raise TransportError(f"bad device URL {url!r}: unknown option{'s' if len(unknown) > 1 else ''} "
                             f"{', '.join(unknown)}; it takes {opts}")
    return q


def _flag(q, name, default):
    v = q.get(name, [default])[0]
    return v


def _board_flags(url: str, q) -> tuple[int, str]:
    """sim:// and emu://'s simulated board: load=OHM (a resistor on every channel; 0: the electrode
    model) and board=real|ideal."""
    try:
        load_ohm = int(_flag(q, "load", "0"))
    except ValueError:
        raise TransportError(f"bad device URL {url!r}: load takes a whole number of ohms, e.g. load=10000") from None
    if load_ohm and not 100 <= load_ohm <= 1_000_000:
        raise TransportError(f"bad device URL {url!r}: load={load_ohm} ohm out of range [100, 1000000]")
    board = _flag(q, "board", "real")
    if board not in ("real", "ideal"):
        raise TransportError(f"bad device URL {url!r}: board is real (the parts' errors, default) or ideal")
    return load_ohm, board


def open_transport(url: str, hid_module=None) -> Transport:
    """Open the transport a device URL names; TransportError with advice otherwise."""
    u = urlsplit(url)
    if u.scheme == "hid":
        spec = (u.netloc + u.path).strip("/")
        ids, _, serial = spec.partition("/")
        try:
            vid_s, pid_s = (ids or f"{hp.VID:04x}:{hp.PID:04x}").split(":")
            vid, pid = int(vid_s, 16), int(pid_s, 16)
        except ValueError:
            raise TransportError(f"bad device URL {url!r}: use hid://VID:PID[/SERIAL] in hex, e.g. {DEFAULT_URL}") from None
        return HidTransport(vid, pid, serial or None, hid_module)
    if u.scheme == "sim":
        q = _known_options(url, u.query, SIM_OPTIONS)
        scenario = (u.netloc + u.path) or "steady"
        try:
            channels = int(_flag(q, "channels", "2"))
            seed = int(_flag(q, "seed", "1"))
            frames = int(_flag(q, "frames", "0")) or None
        except ValueError:
            raise TransportError(f"bad device URL {url!r}: channels, seed and frames take whole numbers") from None
        load_ohm, board = _board_flags(url, q)
        realtime = _flag(q, "realtime", "1").lower()
        if realtime not in _YES + _NO:
            raise TransportError(f"bad device URL {url!r}: realtime={realtime} is not one of {SIM_OPTIONS['realtime']}")
        realtime = realtime in _YES
        from .simrun import SimError, scenario_keys

        try:
            scenario_keys(scenario)  # a missing, binary or unbounded scenario: one line, before the VM starts
        except SimError as e:
            raise TransportError(f"bad device URL {url!r}: {e}") from None
        mode = _flag(q, "mode", "akhtar")
        if mode not in ("akhtar", "fast", "open", "charge", "energy", "pwlinear"):
            raise TransportError(f"bad device URL {url!r}: mode is akhtar, fast, open, charge, energy or pwlinear")
        return SimTransport(scenario, channels, seed, realtime, _flag(q, "auto", None), mode, frames,
                            board == "ideal", load_ohm)
    if u.scheme == "emu+tcp":
        try:
            port = u.port
        except ValueError:
            port = None
        if not u.hostname or port is None or not 1 <= port <= 65535 or u.path.strip("/") or u.query:
            raise TransportError(f"bad device URL {url!r}: use emu+tcp://HOST:PORT with PORT in [1, 65535], "
                                 "e.g. emu+tcp://127.0.0.1:40124")
        return EmuTcpTransport(u.hostname, port)
    if u.scheme == "emu":
        q = _known_options(url, u.query, EMU_OPTIONS)
        scenario = (u.netloc + u.path).strip("/") or _flag(q, "scenario", "steady")
        try:
            channels = int(_flag(q, "channels", "2"))
            seed = int(_flag(q, "seed", "1"))
        except ValueError:
            raise TransportError(f"bad device URL {url!r}: channels and seed take whole numbers") from None
        if not 1 <= channels <= 4:
            raise TransportError(f"bad device URL {url!r}: channels={channels} out of range [1, 4]")
        if not 0 <= seed < 2**32:
            raise TransportError(f"bad device URL {url!r}: seed={seed} out of range [0, 2**32)")
        auto = _flag(q, "auto", None)
        if auto is not None:
            try:
                auto = tuple(int(v) for v in auto.split(","))
                if len(auto) != 4:
                    raise ValueError
            except ValueError:
                raise TransportError(f"bad device URL {url!r}: auto takes I0_UA,T0_US,XSTAR_OHM,YSTAR_PC, "
                                     "e.g. auto=1000,1000,-1670,186000") from None
            from .protocol import check_calibration

            try:
                check_calibration(*auto)
            except ValueError as e:
                raise TransportError(f"bad device URL {url!r}: auto: {e}") from None
        load_ohm, board = _board_flags(url, q)
        from .simrun import SimError, scenario_keys

        try:
            scenario_keys(scenario)
        except SimError as e:
            raise TransportError(f"bad device URL {url!r}: {e}") from None
        return EmuTransport(scenario, channels, seed, auto, load_ohm, board == "ideal")
    raise TransportError(f"unknown device {url!r}: use {DEFAULT_URL} (the board over USB), sim://SCENARIO "
                         "(the simulator, e.g. sim://peel), emu://SCENARIO (the firmware on the emulated Pico) or "
                         "emu+tcp://HOST:PORT (an emulated Pico already served)")
