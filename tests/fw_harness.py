"""Run firmware scenarios in the real MicroPython VM and bring the reports home."""

import json
import os
import subprocess
import textwrap

from steadytouch.protocol import decode

from conftest import FIRMWARE, SHARED, tool

PRELUDE = """
import sys, json
import board_config as cfg
import hid_protocol as hp
import sensation_core as sc
import stim, board_sim, sim_electrode
from board_sim import SimBoard, VirtualClock, MemoryUSB

def make(scenario="steady", n=2, start=0, seed=1, keep=True, rate=50, keepalive_ms=0, ideal=True):
    clock = VirtualClock(start)
    usb = MemoryUSB(keep)
    sce = sim_electrode.scenario(scenario)
    # the ideal board: these tests check the firmware's logic and math (the realistic board: test_board_sim.py)
    board = SimBoard(cfg, clock, sce, n, seed, usb, ideal=ideal)
    s = stim.Stimulator(board, clock, cfg, n, rate, keepalive_ms)
    return s, board, usb, clock

def command(s, rep):
    s.board.usb.inbox.append(bytes(rep))

def apply(s, rep):
    r = s.handle(bytearray(rep), s.clock.ticks_us())
    s.sync_outputs()
    return r

def start(s, i0=1000, t0=1000, x=-1670, y=186000, mode=sc.MODE_AKHTAR, limits=None):
    b = bytearray(64)
    if limits:
        assert apply(s, hp.cmd_set_limits(b, *limits)) == 0
    assert apply(s, hp.cmd_set_mode(b, mode)) == 0
    assert apply(s, hp.cmd_calibrate(b, hp.CH_ALL, i0, t0, x, y)) == 0
    assert apply(s, hp.cmd_arm(b, hp.CH_ALL)) == 0

def dump(usb):
    for r in usb.sent:
        print("R " + "".join("%02x" % v for v in r))
    usb.sent.clear()

def result(**kw):
    print("J " + json.dumps(kw))
"""


def run_fw(body: str, timeout=300, micropython=None):
    """Run PRELUDE + body in the MicroPython VM; returns (reports, results, proc)."""
    mp = micropython or tool("micropython")
    env = dict(os.environ, MICROPYPATH=os.pathsep.join([str(SHARED), str(FIRMWARE)]))
    script = PRELUDE + textwrap.dedent(body)
    p = subprocess.run([mp, "-c", script], capture_output=True, text=True, timeout=timeout, env=env)
    if p.returncode != 0:
        raise AssertionError(f"MicroPython failed ({p.returncode}):\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}")
    reports, results = [], []
    for line in p.stdout.splitlines():
        if line.startswith("R "):
            reports.append(decode(bytes.fromhex(line[2:])))
        elif line.startswith("J "):
            results.append(json.loads(line[2:]))
    return reports, results, p
