# Runs in the MicroPython VM: one Stimulator on the simulated board; reads one
# hex OUT report per line from stdin, applies it, runs one frame, and prints
# "<ack report hex> <state digest>" (the digest covers every setting a command
# may change). A line "F n" runs n frames and prints the digest.
import sys

import board_config as cfg
import board_sim
import sim_electrode
import stim

clock = board_sim.VirtualClock()
usb = board_sim.MemoryUSB(keep=False)
board = board_sim.SimBoard(cfg, clock, sim_electrode.scenario("steady"), 2, 1, usb)
s = stim.Stimulator(board, clock, cfg, 2, 50)
rx = bytearray(64)


def digest():
    parts = [s.mode, s.rate_hz, s.keepalive_ms] + list(s.lim)
    for c in s.chans:
        ctl = c.ctl
        parts += [int(c.armed), c.stop, int(c.have_cal), c.i0, c.t0, c.x, c.y, int(c.calibrating),
                  ctl.mode, ctl.i_min_ua, ctl.i_max_ua, ctl.t_min_us, ctl.t_max_us, ctl.q_max_pc]
    return ",".join([str(p) for p in parts])


print("READY " + digest())
while True:
    line = sys.stdin.readline()
    if not line or not line.strip():
        break
    line = line.strip()
    if line.startswith("F "):
        s.run(int(line[2:]))
        print("F " + digest() + " " + str(s.errors))
        continue
    b = bytes.fromhex(line)
    for k in range(64):
        rx[k] = b[k]
    s.handle(rx, clock.ticks_us())
    ack = "".join(["%02x" % v for v in s.tx])
    s.sync_outputs()
    print(ack + " " + digest() + " " + str(s.errors))
