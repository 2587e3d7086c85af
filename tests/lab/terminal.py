"""The steadytouch command on a pseudo-terminal, as a person runs it: stdin, stdout and
stderr are the terminal (so the status lines are drawn), the command is the terminal's
foreground process group, and a Ctrl-C is the byte 0x03 typed into it, which the
terminal turns into SIGINT for its whole foreground group, as a keyboard does."""

from __future__ import annotations

import fcntl
import os
import pty
import re
import signal
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
EXE = str(Path(sys.executable).parent / "steadytouch")
CTRL_C = b"\x03"


def _controlling_terminal():
    os.setsid()
    fcntl.ioctl(0, termios.TIOCSCTTY, 0)


class Terminal:
    def __init__(self, *args: str, env: dict | None = None, cols: int = 200):
        master, slave = pty.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, bytes(4) if cols is None else
                    (50).to_bytes(2, "little") + cols.to_bytes(2, "little") + bytes(4))
        self.master = master
        self.p = subprocess.Popen([EXE, *args], stdin=slave, stdout=slave, stderr=slave, cwd=ROOT,
                                  env=dict(os.environ, **(env or {})), preexec_fn=_controlling_terminal)
        os.close(slave)
        self.buf = bytearray()
        self.lock = threading.Lock()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self):
        while True:
            try:
                data = os.read(self.master, 65536)
            except OSError:  # EIO: every holder of the terminal's other side is gone
                return
            if not data:
                return
            with self.lock:
                self.buf += data

    @property
    def text(self) -> str:
        with self.lock:
            return self.buf.decode(errors="replace")

    def wait_for(self, pattern: str, timeout_s: float = 60.0, kill: bool = True) -> re.Match:
        """The first match of pattern in what the terminal showed; fails naming what it showed
        (and, with kill, ends the command)."""
        end = time.monotonic() + timeout_s
        while True:
            m = re.search(pattern, self.text)
            if m:
                return m
            if time.monotonic() > end or self.p.poll() is not None and not self.reader.is_alive():
                if kill:
                    self.kill()
                raise AssertionError(f"{pattern!r} not shown within {timeout_s} s; the terminal showed:\n{self.text[-3000:]}")
            time.sleep(0.05)

    def type(self, data: bytes) -> None:
        os.write(self.master, data)

    def finish(self, timeout_s: float = 30.0) -> tuple[int, str]:
        """(exit code, everything the terminal showed) once the command ended."""
        try:
            rc = self.p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"still running {timeout_s} s later; the terminal showed:\n{self.text[-3000:]}")
        self.reader.join(5)
        os.close(self.master)
        return rc, self.text

    def kill(self) -> None:
        if self.p.poll() is None:
            try:
                os.killpg(self.p.pid, signal.SIGKILL)  # its own session: nothing else is in this group
            except ProcessLookupError:
                pass
            self.p.wait(10)


def status_lines(text: str, what: str) -> list[str]:
    """The status lines drawn in place (after a carriage return and erase-line) for `what`."""
    return re.findall(r"\r\x1b\[K(" + re.escape(what) + r": \d+ pulses, [^\r\n]*)", text)
