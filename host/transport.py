"""Transports: one interface, chosen by a URL-like device name (in the spirit of
pyserial's `loop://` handlers).

- `hid://VID:PID[/SERIAL]` — the board over USB HID, through hidapi
  (hidraw backend on Linux when available). Default: `hid://1209:0001`.
- `sim://SCENARIO[?channels=N&seed=S&realtime=0|1&auto=I0,T0,X,Y&mode=akhtar|open]`
  — the real firmware in the MicroPython VM with the simulated board, speaking
  the same report stream on its stdio.

Every transport moves whole 64-byte reports: `read(timeout_s)` returns one IN
report or None on timeout, `write(report)` sends one OUT report. Decoding, gap
detection and commands live above, in `device.py`, the same for all.
"""

from __future__ import annotations

import queue
import subprocess
import sys
import threading
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

    def read(self, timeout_s: float) -> bytes | None:
        raise NotImplementedError

    def write(self, report: bytes) -> None:
        raise NotImplementedError

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
                 auto: str | None = None, mode: str = "akhtar", frames: int | None = None):
        from .simrun import FIRMWARE, micropython_exe, vm_popen

        self.url = f"sim://{scenario}"
        self.realtime = realtime
        args = [micropython_exe(), str(FIRMWARE / "main.py"), "--scenario", scenario, "--channels", str(channels),
                "--seed", str(seed), "--mode", mode, "--exit-on-eof"]
        if realtime:
            args.append("--realtime")  # the board's keep-alive, on the host's time line
        else:
            args += ["--keepalive-ms", "0"]  # virtual time outruns any host: off (docs/safety.md)
        if auto:
            args += ["--auto", auto]
        if frames:
            args += ["--frames", str(frames)]
        self.p = vm_popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=0)
        self.q: queue.Queue = queue.Queue(maxsize=100000)
        self.error = ""
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
            msg = f"the simulated device stopped (exit code {self.p.returncode})"
            raise Disconnected(msg + (f": {self.error}" if self.error else ""))
        return r

    def write(self, report: bytes) -> None:
        try:
            self.p.stdin.write(b"\xa5\x5a" + bytes(report))
            self.p.stdin.flush()
        except (BrokenPipeError, OSError):
            raise Disconnected("the simulated device stopped") from None

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


def _flag(q, name, default):
    v = q.get(name, [default])[0]
    return v


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
        q = parse_qs(u.query)
        scenario = (u.netloc + u.path) or "steady"
        try:
            channels = int(_flag(q, "channels", "2"))
            seed = int(_flag(q, "seed", "1"))
            frames = int(_flag(q, "frames", "0")) or None
        except ValueError:
            raise TransportError(f"bad device URL {url!r}: channels, seed and frames take whole numbers") from None
        realtime = _flag(q, "realtime", "1") not in ("0", "no", "false")
        from .simrun import SimError, scenario_keys

        try:
            scenario_keys(scenario)  # a missing, binary or unbounded scenario: one line, before the VM starts
        except SimError as e:
            raise TransportError(f"bad device URL {url!r}: {e}") from None
        mode = _flag(q, "mode", "akhtar")
        if mode not in ("akhtar", "fast", "open", "charge", "energy", "pwlinear"):
            raise TransportError(f"bad device URL {url!r}: mode is akhtar, fast, open, charge, energy or pwlinear")
        return SimTransport(scenario, channels, seed, realtime, _flag(q, "auto", None), mode, frames)
    raise TransportError(f"unknown device {url!r}: use {DEFAULT_URL} (the board over USB) or sim://SCENARIO "
                         "(the simulator, e.g. sim://peel)")
