"""The board's USB libraries, pinned: micropython-lib's usb-device 0.2.1 and
usb-device-hid 0.1.2 (MIT) at the commit MicroPython v1.28.0 pins.

The project does not carry their code; it carries this lock (commit, paths and
sha256 of every file) and takes the files from a folder that matches it:
`--lib-dir DIR`, else the cache that `steadytouch flash --online` fills once
from GitHub. Any file that does not match its hash is refused, so whatever
folder they come from, the board gets exactly the pinned version.
"""

from __future__ import annotations

import hashlib
import os
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

COMMIT = "8380c7bb8f9e5e5260e9539156742925e00366b2"  # micropython-lib, pinned by MicroPython v1.28.0
PACKAGES = (("usb-device", "0.2.1"), ("usb-device-hid", "0.1.2"))
URL = "https://raw.githubusercontent.com/micropython/micropython-lib/{commit}/{path}"


@dataclass(frozen=True)
class LibFile:
    board: str  # path under the board's /lib
    upstream: str  # path in micropython-lib
    sha256: str


FILES = (
    LibFile("usb/device/__init__.py", "micropython/usb/usb-device/usb/device/__init__.py",
            "c8d3315a67057aa55ba5addb3dc28a690bb468c1f518d17e89d8679bed098a10"),
    LibFile("usb/device/core.py", "micropython/usb/usb-device/usb/device/core.py",
            "40ffb6b24e8ec2b18f88afbde8e16c548278385a346f2f5847d11086e565774b"),
    LibFile("usb/device/hid.py", "micropython/usb/usb-device-hid/usb/device/hid.py",
            "623e7d1f560a284bff986c07a47153d575b68a69c51f255d17612bfa636063e7"),
)
LICENSE = LibFile("LICENSE", "LICENSE", "a38cf48836aa313254cdcf3de9fb7c24da4a2eab75ead2cc0cecd998336e7800")
NAME = " + ".join(f"{n} {v}" for n, v in PACKAGES) + f" (micropython-lib {COMMIT[:8]})"


class LibError(RuntimeError):
    pass


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "steadytouch" / f"micropython-lib-{COMMIT[:8]}"


def _sha256(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _find(folder: Path, f: LibFile) -> Path | None:
    """The file in the board's layout (usb/device/x.py) or a micropython-lib checkout's."""
    for rel in (f.board, f.upstream):
        p = folder / rel
        if p.is_file():
            return p
    return None


def check_folder(folder: Path) -> dict[str, Path]:
    """The pinned files in `folder`, each checked against its sha256; LibError names what is wrong."""
    if not folder.is_dir():
        raise LibError(f"{folder} is not a folder")
    found = {}
    for f in FILES + (LICENSE,):
        p = _find(folder, f)
        if p is None:
            raise LibError(f"{folder} has no {f.board} (expected {NAME}, laid out as usb/device/*.py "
                           "or as a micropython-lib checkout)")
        got = _sha256(p)
        if got != f.sha256:
            raise LibError(f"{p} is not the pinned {f.board} of {NAME}: sha256 {got[:12]}..., expected "
                           f"{f.sha256[:12]}...; refusing an unknown version")
        found[f.board] = p
    return found


def fetch(dest: Path, url: str = URL, timeout_s: float = 20) -> dict[str, Path]:
    """Download the pinned files from GitHub into `dest` (checked before they are kept)."""
    for f in FILES + (LICENSE,):
        u = url.format(commit=COMMIT, path=f.upstream)
        try:
            with urllib.request.urlopen(u, timeout=timeout_s) as r:
                data = r.read()
        except (urllib.error.URLError, OSError) as e:
            reason = getattr(e, "reason", e)
            raise LibError(f"cannot download {u} ({reason}); without internet, give a copy of the pinned "
                           f"files with --lib-dir DIR (see docs/hardware.md)") from None
        got = hashlib.sha256(data).hexdigest()
        if got != f.sha256:
            raise LibError(f"{u} does not match the pinned sha256 ({got[:12]}... instead of {f.sha256[:12]}...): "
                           "refusing it")
        p = dest / f.board
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(p.name + ".part")
        tmp.write_bytes(data)
        tmp.replace(p)
    return check_folder(dest)


def locate(lib_dir: str | None, online: bool, url: str = URL) -> tuple[dict[str, Path], str]:
    """The pinned files and where they came from: --lib-dir, the cache, or (--online) GitHub."""
    if lib_dir:
        return check_folder(Path(lib_dir)), f"from {lib_dir}"
    cache = cache_dir()
    if cache.is_dir():
        try:
            return check_folder(cache), f"from the cache {cache}"
        except LibError:
            if not online:
                raise LibError(f"the cache {cache} does not hold {NAME}: delete it and run "
                               "`steadytouch flash --online` once, or give a copy with --lib-dir DIR") from None
    if online:
        return fetch(cache, url), f"downloaded from GitHub into {cache}"
    raise LibError(f"the board's USB libraries ({NAME}) are not on this computer: run `steadytouch flash --online` "
                   f"once with internet (they are kept in {cache} for offline use), or give a copy with --lib-dir DIR")
