"""`python -m steadytouch.emu serve`: an emulated Pico (the real MicroPython rp2 firmware in
rp2040js, ../shared/emulator) as a plugged-in board: its USB serial and its HID interface
on two TCP ports on 127.0.0.1, until Ctrl-C. A blank board unless --fs-image; its flash
survives its resets. Try `steadytouch flash` on it:

  steadytouch flash --port socket://127.0.0.1:PORT --device emu+tcp://127.0.0.1:PORT2
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from . import ChipError, ChipUnavailable, serve_host


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m steadytouch.emu", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("serve", help="serve an emulated Pico's USB serial and HID interface on 127.0.0.1")
    s.add_argument("--fs-image", type=Path, help="the board's filesystem (littlefs image at flash 0xa0000)")
    s.add_argument("--save-fs", type=Path, help="save the board's filesystem here on exit")
    s.add_argument("--seconds", type=float, default=0, help="stop after this many seconds (default: Ctrl-C)")
    s.add_argument("--log", type=Path, help="the emulator's progress lines (default: a temporary file)")
    a = ap.parse_args(argv)
    if a.fs_image and not a.fs_image.is_file():
        ap.exit(2, f"{ap.prog}: --fs-image {a.fs_image}: no such file\n")
    log = a.log or Path(tempfile.mkstemp(prefix="steadytouch-emu-", suffix=".log")[1])
    try:
        host = serve_host(log)
    except ChipUnavailable as e:
        ap.exit(2, f"{ap.prog}: {e}\n")
    try:
        cdc, hid = host.serve(a.fs_image, a.save_fs, a.seconds)
        print(f"serial (mpremote, flash --port): socket://127.0.0.1:{cdc}\n"
              f"HID (--device):                   emu+tcp://127.0.0.1:{hid}\n"
              f"emulator log: {log}; Ctrl-C stops the board", flush=True)
        while host.p.poll() is None:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    except ChipError as e:
        ap.exit(2, f"{ap.prog}: {str(e).splitlines()[0]}\n")
    finally:
        host.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
