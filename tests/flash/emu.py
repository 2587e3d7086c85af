"""The emulated Pico for the flash tests: ../shared/emulator/rp2tcp.mjs (real
MicroPython v1.28.0 for the RP2040 in rp2040js) serving the board's USB serial
on 127.0.0.1, reached as socket://127.0.0.1:PORT.

rp2run.mjs imports `rp2040js` by bare name, which Node resolves next to the
importing file (not through NODE_PATH), so the runner is copied into an ignored
cache folder (.cache/flash/emu) beside an `npm install` of the pinned rp2040js;
the firmware image and boot ROM are used in place.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
EMU = ROOT.parent / "shared" / "emulator"
CACHE = ROOT / ".cache" / "flash" / "emu"
RP2040JS = "1.4.1"
SKIP_REASON = (f"emulated Pico not found ({EMU}): the flash end-to-end tests need ../shared/emulator "
               "(rp2tcp.mjs, firmware.uf2) beside the checkout and Node >= 20")


def available() -> bool:
    return (EMU / "rp2tcp.mjs").is_file() and (EMU / "firmware.uf2").is_file() and shutil.which("node") is not None


def prepare() -> Path:
    """The runner folder: rp2run.mjs beside node_modules/rp2040js (npm install, pinned), uf2 and boot ROM linked."""
    CACHE.mkdir(parents=True, exist_ok=True)
    pkg = CACHE / "package.json"
    want = {"name": "steadytouch-flash-emu", "private": True, "type": "module",
            "dependencies": {"rp2040js": RP2040JS}}
    if not pkg.is_file() or json.loads(pkg.read_text()) != want:
        pkg.write_text(json.dumps(want, indent=1) + "\n")
    installed = CACHE / "node_modules" / "rp2040js" / "package.json"
    if not installed.is_file() or json.loads(installed.read_text()).get("version") != RP2040JS:
        subprocess.run(["npm", "install", "--no-audit", "--no-fund", "--silent"], cwd=CACHE, check=True,
                       capture_output=True, timeout=300)
    shutil.copyfile(EMU / "rp2run.mjs", CACHE / "rp2run.mjs")
    for name in ("firmware.uf2", "bootrom-b1.bin"):
        link = CACHE / name
        if not link.exists():
            link.symlink_to(EMU / name)
    return CACHE


class Pico:
    """One emulated board: `with Pico(log) as b:` ... `b.url`; stops (SIGTERM) on exit, saving its flash."""

    def __init__(self, log: Path, seconds: int = 600, fs_image: Path | None = None, save_fs: Path | None = None):
        self.log_path = log
        self.args = ["node", str(EMU / "rp2tcp.mjs"), "--emu", str(prepare()), "--seconds", str(seconds),
                     "--reenumerate"]
        if fs_image:
            self.args += ["--fs-image", str(fs_image)]
        if save_fs:
            self.args += ["--save-fs", str(save_fs)]
        self.proc = None
        self.url = None

    def __enter__(self) -> Pico:
        self.log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=self.log)
        line = self.proc.stdout.readline().decode()
        if not line.startswith("PORT "):
            self.stop()
            raise RuntimeError(f"rp2tcp.mjs did not start: {line!r}; see {self.log_path}")
        self.url = f"socket://127.0.0.1:{int(line.split()[1])}"
        return self

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc and self.proc.stdout:
            self.proc.stdout.close()
        self.log.close()

    def __exit__(self, *exc) -> None:
        self.stop()

    def stderr(self) -> str:
        self.log.flush()
        return self.log_path.read_text(errors="replace")


def wait_for_text(pico: Pico, text: str, timeout_s: float) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if text in pico.stderr():
            return True
        time.sleep(0.2)
    return False


