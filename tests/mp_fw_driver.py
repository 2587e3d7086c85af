# Runs in the MicroPython VM: one Stimulator on the simulated board; reads one
# hex OUT report per line from stdin, delivers it through the board's USB and
# runs one frame (so it is handled heap-locked, as on the device), and prints
# "<ack report hex> <state digest>" (the digest covers every setting a command
# may change). A line "F n" runs n frames and prints the digest.
import sys


import board_config as cfg
import board_sim
import sim_electrode
import stim
import mp_watch

clock = board_sim.VirtualClock()
usb = board_sim.MemoryUSB(keep=True)
board = board_sim.SimBoard(cfg, clock, sim_electrode.scenario("steady"), 2, 1, usb)
s = stim.Stimulator(board, clock, cfg, 2, 50)


def digest():
    parts = [s.mode, s.rate_hz, s.keepalive_ms] + list(s.lim)
    for c in s.chans:
        ctl = c.ctl
        parts += [int(c.armed), c.stop, int(c.have_cal), c.i0, c.t0, c.x, c.y, int(c.calibrating),
                  ctl.mode, ctl.i_min_ua, ctl.i_max_ua, ctl.t_min_us, ctl.t_max_us, ctl.q_max_pc,
                  ctl.skin_rs_ohm, ctl.skin_beta_q16, ctl.skin_cp_pf]
    return ",".join([str(p) for p in parts])


seen = mp_watch.watch(s, digest)
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
    usb.sent.clear()
    usb.inbox.append(bytes.fromhex(line))
    s.run(1)  # the report is handled inside a real frame, heap-locked like on the board
    acks = [r for r in usb.sent if r[0] != 1]
    usb.sent.clear()
    ack = "".join(["%02x" % v for v in acks[0]]) if len(acks) == 1 else "none"
    print(ack + " " + seen[0] + " " + seen[1] + " " + str(s.errors))
