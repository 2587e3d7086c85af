"""The OUT reports' CRC on the emulated chip: the table-driven crc16 gives the same
CRC as CPython and takes a fraction of the
bit-by-bit version's ~5 ms (emulated us: deterministic). It runs
heap-locked inside the firmware's command handler (tests/chip/test_chip_main.py)."""

import random
import sys

from .harness import SHARED

sys.path.insert(0, str(SHARED))
import hid_protocol as hp  # noqa: E402


def test_crc16_on_chip_matches_cpython_fast(chip):
    r = random.Random(12)
    bufs = [bytes(r.randrange(256) for _ in range(64)) for _ in range(8)] + [b"123456789" + bytes(55)]
    out = chip.eval_out(
        "import time, hid_protocol as hp\n"
        f"bufs = [bytearray(x) for x in {bufs!r}]\n"
        "res = []\n"
        "us = []\n"
        "for b in bufs:\n"
        "    t0 = time.ticks_us()\n"
        "    c = hp.crc16(b, hp.CRC_LEN)\n"
        "    t1 = time.ticks_us()\n"
        "    res.append(c)\n"
        "    us.append(time.ticks_diff(t1, t0))\n"
        "print((res, hp.crc16(bufs[-1], 9), max(us)))")
    crcs, check, worst_us = out
    assert crcs == [hp.crc16(b, hp.CRC_LEN) for b in bufs]
    assert check == 0x29B1  # CRC-16/CCITT-FALSE check value of "123456789"
    assert worst_us < 1500, worst_us  # bit by bit it was ~5080 us
