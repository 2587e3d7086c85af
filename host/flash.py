"""Compile the device's files with mpy-cross and deploy them with mpremote."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from .simrun import FIRMWARE, SHARED

# files the board does not need (the simulator and the demo)
HOST_ONLY = {"board_sim.py", "sim_electrode.py", "worked_example.py"}
SOURCE_FILES = {"main.py"}  # kept as .py: MicroPython runs main.py at boot
RP2_VID = 0x2E8A


class FlashError(RuntimeError):
    pass


def device_files() -> list[Path]:
    return sorted(SHARED.glob("*.py")) + sorted(p for p in FIRMWARE.glob("*.py") if p.name not in HOST_ONLY)


def _tool(name: str) -> str:
    p = Path(sys.executable).parent / name
    if p.exists():
        return str(p)
    found = shutil.which(name)
    if not found:
        raise FlashError(f"{name} is not installed: run `make setup`")
    return found


def build(out: Path) -> list[Path]:
    """Compile for the RP2040 (armv6m) into `out`; returns the files written."""
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    written = []
    for src in device_files():
        if src.name in SOURCE_FILES:
            dst = out / src.name
            shutil.copy(src, dst)
        else:
            dst = out / (src.stem + ".mpy")
            p = subprocess.run([_tool("mpy-cross"), "-march=armv6m", "-o", str(dst), str(src)],
                               capture_output=True, text=True)
            if p.returncode:
                raise FlashError(f"mpy-cross failed on {src.name}: {p.stderr.strip()}")
        written.append(dst)
    return written


def find_port() -> str:
    from serial.tools import list_ports

    ports = [p.device for p in list_ports.comports() if p.vid == RP2_VID]
    if not ports:
        raise FlashError("no Raspberry Pi Pico found (USB VID 0x2E8A): connect it with MicroPython >= 1.23 "
                         "flashed (hold BOOTSEL while plugging in to install MicroPython first)")
    return ports[0]


def deploy_commands(port: str, out: Path) -> list[list[str]]:
    mp = _tool("mpremote")
    cmds = [[mp, "connect", port, "mip", "install", "usb-device-hid"]]
    for f in sorted(out.iterdir()):
        cmds.append([mp, "connect", port, "cp", str(f), f":{f.name}"])
    cmds.append([mp, "connect", port, "reset"])
    return cmds
