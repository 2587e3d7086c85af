"""Fixtures of the chip tests: the real MicroPython firmware for the Pico on the
emulated RP2040 (rp2040js, pinned in tests/chip/package.json and its lock,
installed by npm into .cache/chip), with the project's device files compiled for
armv6m in the board's /lib. ../shared/emulator (firmware.uf2, boot ROM, runner)
is used in place; without it every chip test skips with one line."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import shutil
import subprocess
from pathlib import Path

import pytest

from conftest import FIRMWARE, ROOT, SHARED, compile_mpy

from .harness import Host

EMULATOR = ROOT.parent / "shared" / "emulator"
CACHE = ROOT / ".cache" / "chip"
HERE = Path(__file__).resolve().parent
RP2040JS = "1.4.1"
# on the board: everything the rp2 build needs but main.py (it would start the loop at boot)
HOST_ONLY = {"board_sim.py", "sim_electrode.py", "worked_example.py", "main.py"}
SKIP = ("chip tests skipped: ../shared/emulator is absent (the Pico's MicroPython firmware.uf2, boot ROM and "
        "rp2run.mjs beside the checkout; build it with its build-firmware.sh, see docs/hardware.md)")


def load_cfg():
    spec = importlib.util.spec_from_file_location("board_config_chip", FIRMWARE / "board_config.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _tool(name: str) -> str:
    p = shutil.which(name)
    if not p:
        pytest.fail(f"the chip tests need {name} (Node >= 20 with npm); ../shared/emulator is present")
    return p


def _install_rp2040js() -> None:
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
    if p.returncode or json.loads(pkg.read_text())["version"] != RP2040JS:
        pytest.fail(f"npm could not install rp2040js {RP2040JS} into {CACHE}: {p.stderr.strip()[-400:]}")


def _device_files(mpy_cross: str, out: Path) -> list[tuple[Path, str]]:
    """(local .mpy, path on the board) for the project's device files and board-lib."""
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    files = []
    for src in sorted(SHARED.glob("*.py")) + sorted(FIRMWARE.glob("*.py")):
        if src.name not in HOST_ONLY:
            files.append((compile_mpy(mpy_cross, src, out, "-march=armv6m", "-s", src.name), "/lib/" + src.stem + ".mpy"))
    lib = EMULATOR / "board-lib"
    for src in sorted(lib.rglob("*.py")):
        rel = src.relative_to(lib)
        d = out / rel.parent
        d.mkdir(parents=True, exist_ok=True)
        files.append((compile_mpy(mpy_cross, src, d, "-march=armv6m", "-s", src.name),
                      "/lib/" + str(rel.with_suffix(".mpy"))))
    return files


@pytest.fixture(scope="session")
def chip_host(mpy_cross):
    """The Node host with a flash image holding the device files (built once, cached by content)."""
    if not (EMULATOR / "firmware.uf2").exists() or not (EMULATOR / "rp2run.mjs").exists():
        pytest.skip(SKIP)
    node = _tool("node")
    _install_rp2040js()
    files = _device_files(mpy_cross, CACHE / "mpy")
    h = hashlib.sha256((EMULATOR / "firmware.uf2").read_bytes())
    for local, remote in files:
        h.update(remote.encode() + local.read_bytes())
    image = CACHE / f"fs-{h.hexdigest()[:16]}.img"
    host = Host(node, EMULATOR, CACHE, CACHE / "host.log")
    try:
        if not image.exists():
            chip = host.boot()
            chip.exec("import os\nfor d in ('/lib', '/lib/usb', '/lib/usb/device'):\n"
                      "    try:\n        os.mkdir(d)\n    except OSError:\n        pass")
            for local, remote in files:
                chip.put(local.read_bytes(), remote)
            for old in CACHE.glob("fs-*.img"):
                old.unlink()
            chip.save_fs(image)
        host.image = image
        yield host
    finally:
        host.close()


@pytest.fixture()
def chip(chip_host):
    """A freshly booted chip (the device files in /lib), no board constructed yet."""
    return chip_host.boot(chip_host.image)


@pytest.fixture(scope="session")
def cfg():
    return load_cfg()
