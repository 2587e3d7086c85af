"""The emulated Pico for the flash tests: host/emu/host.mjs's `serve` (real MicroPython
v1.28.0 for the RP2040 in rp2040js, ../shared/emulator used in place) boots a board from
its flash as at power-up and plays its USB cable on 127.0.0.1: the USB serial as
socket://127.0.0.1:PORT (mpremote, `flash --port`), the HID interface as
emu+tcp://127.0.0.1:PORT2 (`flash --device`, every host command). A hard reset reboots
the chip with its flash kept, as on a real Pico; the host's log has one line per event
(`hard reset, REASON`, `emulated host: enumerating again`, HID client report counts).
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

from steadytouch import emu as E

EMU = E.EMULATOR
SKIP_REASON = (f"emulated Pico not found ({EMU}): the flash end-to-end tests need ../shared/emulator "
               "(rp2run.mjs, firmware.uf2; see its README) beside the checkout and Node >= 20")


def available() -> bool:
    return (EMU / "rp2run.mjs").is_file() and (EMU / "firmware.uf2").is_file() and shutil.which("node") is not None


class Pico:
    """One emulated board: `with Pico(log) as b:` ... `b.url` (serial), `b.hid_url` (HID);
    stops on exit (its filesystem saved to save_fs if given)."""

    def __init__(self, log: Path, seconds: int = 600, fs_image: Path | None = None, save_fs: Path | None = None):
        self.log_path = log
        self.seconds = seconds
        self.fs_image = fs_image
        self.save_fs = save_fs
        self.host = None
        self.url = self.hid_url = None

    def __enter__(self) -> Pico:
        self.host = E.serve_host(self.log_path)
        try:
            cdc, hid = self.host.serve(self.fs_image, self.save_fs, self.seconds)
        except BaseException:
            self.host.close()
            raise
        self.url = f"socket://127.0.0.1:{cdc}"
        self.hid_url = f"emu+tcp://127.0.0.1:{hid}"
        return self

    def stop(self) -> None:
        if self.host is not None:
            self.host.close()
            self.host = None

    def __exit__(self, *exc) -> None:
        self.stop()

    def stderr(self) -> str:
        return self.log_path.read_text(errors="replace")


def wait_for_text(pico: Pico, text: str, timeout_s: float) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if text in pico.stderr():
            return True
        time.sleep(0.2)
    return False
