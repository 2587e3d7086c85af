# Seeded command fuzz of the whole firmware, run inside the MicroPython VM:
#   micropython tests/mp_fuzz.py SEED N
# (MICROPYPATH = shared:firmware). Each of N OUT reports is delivered through the
# simulated board's USB and handled inside a real frame (heap-locked, as on the
# device). After each one it checks:
#   - a refused report (result != OK) changed nothing (the settings digest);
#   - the device answered exactly once and the frame raised nothing;
#   - every pulse that reached the board: its channel armed, T_FLOOR_US <= t <= hard
#     and soft t_max, i <= hard and soft i_max, i*t <= hard and soft q_max;
#   - the settings stay inside the hard limits (t_min >= T_FLOOR_US, keep-alive on).
# Prints "SEED n" first and one summary line "OK ..." or "FAIL <what>" at the end;
# exit status 0 only if nothing failed. tests/test_fuzz_firmware.py runs it in the
# suite, bench/fuzz.py for millions of reports.
import sys


import board_config as cfg
import board_sim
import hid_protocol as hp
import sensation_core as sc
import sim_electrode
import stim
import mp_watch

SEED = int(sys.argv[1])
N = int(sys.argv[2])
print("SEED %d" % SEED)

_state = [SEED & 0xFFFFFFFF or 1]


def rnd():
    """xorshift32: the same stream in CPython and MicroPython."""
    x = _state[0]
    x ^= (x << 13) & 0xFFFFFFFF
    x ^= x >> 17
    x ^= (x << 5) & 0xFFFFFFFF
    _state[0] = x
    return x


def below(n):
    return rnd() % n


clock = board_sim.VirtualClock()
usb = board_sim.MemoryUSB(keep=True)
board = board_sim.SimBoard(cfg, clock, sim_electrode.scenario("steady"), 2, SEED, usb)
s = stim.Stimulator(board, clock, cfg, 2, 50)

COMMANDS = (hp.CMD_ARM, hp.CMD_DISARM, hp.CMD_CALIBRATE, hp.CMD_SET_LIMITS, hp.CMD_SET_MODE, hp.CMD_KEEPALIVE,
            hp.CMD_GET_INFO, hp.CMD_SET_SKIN)
# values at and around every limit a 16-bit argument field meets
U16 = (0, 1, 2, 19, 20, 21, 49, 50, 51, 99, 100, 101, 499, 500, 1000, 1670, 4000, 7999, 8000, 8001, 9999, 10000,
       10001, 32767, 32768, 65534, 65535)
# and a 32-bit one (as the device reads it: i32, values past +-2**29 read as bad)
I32 = (0, 1, -1, -1670, -20000, -20001, 186000, 999999, 1000000, 8000000, 10000000, 10000001, (1 << 29) - 1,
       1 << 29, -(1 << 29), -(1 << 29) - 1, 0x7FFFFFFF, -0x80000000, 36045, 14000)


def digest():
    parts = [s.mode, s.rate_hz, s.keepalive_ms] + list(s.lim)
    for c in s.chans:
        ctl = c.ctl
        parts += [int(c.armed), int(c.have_cal), c.i0, c.t0, c.x, c.y, ctl.mode, ctl.i_min_ua, ctl.i_max_ua,
                  ctl.t_min_us, ctl.t_max_us, ctl.q_max_pc, ctl.skin_rs_ohm, ctl.skin_beta_q16, ctl.skin_cp_pf]
    return ",".join([str(p) for p in parts])


seen = mp_watch.watch(s, digest)

failures = []
pulses = [0]
fire = board.fire


def checked_fire(ch, t_us):
    c = s.chans[ch]
    i_ua = board.amp[ch]
    lim = s.lim
    if not c.armed:
        failures.append("pulse on disarmed channel %d (i=%d t=%d)" % (ch, i_ua, t_us))
    if not (hp.T_FLOOR_US <= t_us <= s.hard_t and t_us <= lim[3]):
        failures.append("pulse t_us=%d outside [%d, %d]" % (t_us, hp.T_FLOOR_US, min(s.hard_t, lim[3])))
    if not (0 < i_ua <= s.hard_i and i_ua <= lim[1]):
        failures.append("pulse i_ua=%d outside (0, %d]" % (i_ua, min(s.hard_i, lim[1])))
    if i_ua * t_us > s.hard_q or i_ua * t_us > lim[4]:
        failures.append("pulse charge %d pC above %d" % (i_ua * t_us, min(s.hard_q, lim[4])))
    pulses[0] += 1
    return fire(ch, t_us)


board.fire = checked_fire

rep = bytearray(64)
results = {}


def structured():
    for k in range(64):
        rep[k] = rnd() & 0xFF
    rep[hp.O_OUT_CMD] = COMMANDS[below(len(COMMANDS))]
    rep[hp.O_OUT_TAG] = rnd() & 0xFF
    rep[hp.O_OUT_CH] = (0, 1, 2, 3, 0xFF, 0xFF)[below(6)]
    rep[hp.O_OUT_RESERVED] = 0 if below(8) else 1 + below(255)
    for off in (4, 6, 8, 10, 12):
        if below(3):
            hp.put_u16(rep, off, U16[below(len(U16))])
    if below(2):
        off = (4, 6, 8, 10)[below(4)]
        v = I32[below(len(I32))]
        hp.put_u16(rep, off, v & 0xFFFF)
        hp.put_u16(rep, off + 2, (v >> 16) & 0xFFFF)
    if rep[0] == hp.CMD_SET_MODE and below(2):
        rep[hp.O_ARG] = below(8)
        rep[hp.O_ARG + 1] = (0, 9, 10, 50, 100, 101, 255)[below(7)]


# one field of each command (offset, width), for "valid but one field at a limit"
FIELDS = {hp.CMD_CALIBRATE: ((4, 2), (6, 2), (8, 4), (12, 4)), hp.CMD_SET_LIMITS: ((4, 2), (6, 2), (8, 2), (10, 2), (12, 4)),
          hp.CMD_SET_MODE: ((4, 1), (5, 1)), hp.CMD_KEEPALIVE: ((4, 2),), hp.CMD_SET_SKIN: ((4, 2), (6, 4), (10, 4))}


def near_valid():
    """A well-formed command with plausible values, then (half the time) one field
    set to a value at or past a limit: the reports most likely to slip through."""
    cmd = (hp.CMD_CALIBRATE, hp.CMD_SET_LIMITS, hp.CMD_SET_MODE, hp.CMD_KEEPALIVE, hp.CMD_SET_SKIN,
           hp.CMD_DISARM, hp.CMD_ARM)[below(7)]
    ch = (0, 1, 0xFF)[below(3)]
    if cmd == hp.CMD_CALIBRATE:
        i0 = 500 + below(3000)
        t0 = 20 + below(2000)
        hp.cmd_calibrate(rep, ch, i0, t0, -below(5000), below(i0 * t0))
    elif cmd == hp.CMD_SET_LIMITS:
        i_max = 1 + below(s.hard_i)
        t_max = hp.T_FLOOR_US + below(s.hard_t - hp.T_FLOOR_US + 1)
        i_min = 1 + below(i_max)
        t_min = hp.T_FLOOR_US + below(t_max - hp.T_FLOOR_US + 1)
        hp.cmd_set_limits(rep, i_min, i_max, t_min, t_max, i_min * t_min + below(s.hard_q - i_min * t_min + 1))
    elif cmd == hp.CMD_SET_MODE:
        hp.cmd_set_mode(rep, below(6), (0, 10 + below(91))[below(2)])
    elif cmd == hp.CMD_KEEPALIVE:
        hp.cmd_keepalive(rep, hp.KEEPALIVE_MIN_MS + below(hp.KEEPALIVE_MAX_MS - hp.KEEPALIVE_MIN_MS + 1))
    elif cmd == hp.CMD_SET_SKIN:
        hp.cmd_set_skin(rep, ch, below(2000), 20000 + below(40000), 2000 + below(40000))
    elif cmd == hp.CMD_DISARM:
        hp.cmd_disarm(rep, ch)
    else:
        hp.cmd_arm(rep, ch)
    f = FIELDS.get(cmd)
    if f and below(2):
        off, width = f[below(len(f))]
        if width == 1:
            rep[off] = (0, 1, 5, 6, 7, 9, 10, 100, 101, 255)[below(10)]
        elif width == 2:
            hp.put_u16(rep, off, U16[below(len(U16))])
        else:
            v = I32[below(len(I32))]
            hp.put_u16(rep, off, v & 0xFFFF)
            hp.put_u16(rep, off + 2, (v >> 16) & 0xFFFF)
    rep[hp.O_OUT_TAG] = rnd() & 0xFF
    hp.seal(rep)


def valid_start():
    """A plausible calibration and arm, so armed states (and pulses) are common."""
    i0 = 500 + below(3000)
    t0 = s.lim[2] + below(1000)
    if t0 > s.lim[3]:
        t0 = s.lim[3]
    if i0 > s.lim[1]:
        i0 = s.lim[1]
    return [hp.cmd_calibrate(bytearray(64), 0xFF, i0, t0, -below(5000), below(i0 * t0 // 2)),
            hp.cmd_arm(bytearray(64), 0xFF)]


queue = []
n = 0
while n < N and not failures:
    if queue:
        r = queue.pop(0)
    else:
        kind = below(20)
        if kind == 0:
            queue = valid_start()
            continue
        if kind == 1:  # raw bytes: almost always a bad CRC
            for k in range(64):
                rep[k] = rnd() & 0xFF
        elif kind == 2:  # random bytes with a good CRC
            for k in range(64):
                rep[k] = rnd() & 0xFF
            hp.seal(rep)
        elif kind < 12:
            near_valid()
        else:
            structured()
            if below(16):
                hp.seal(rep)
        r = rep
    usb.sent.clear()
    usb.inbox.append(bytes(r))
    before = seen[2]
    s.run(1)
    n += 1
    acks = [a for a in usb.sent if a[0] != hp.REP_TELEMETRY]
    if seen[2] != before + 1 or len(acks) != 1:
        failures.append("report %d: %d answers" % (n, len(acks)))
        break
    a = acks[0]
    res = a[hp.O_RESULT]
    results[res] = results.get(res, 0) + 1
    if res != hp.RES_OK and seen[0] != seen[1]:
        failures.append("report %d refused (result %d) but changed %s -> %s: %s"
                        % (n, res, seen[0], seen[1], bytes(r).hex()))
    if s.errors:
        failures.append("report %d: firmware error %r" % (n, s.last_error))
    lim = s.lim
    if not (1 <= lim[0] <= lim[1] <= s.hard_i and hp.T_FLOOR_US <= lim[2] <= lim[3] <= s.hard_t
            and lim[0] * lim[2] <= lim[4] <= s.hard_q):
        failures.append("report %d: soft limits %r outside the hard ones" % (n, lim))
    if not hp.KEEPALIVE_MIN_MS <= s.keepalive_ms <= hp.KEEPALIVE_MAX_MS:
        failures.append("report %d: keep-alive %d" % (n, s.keepalive_ms))
    if not (sc.MODE_OPEN_LOOP <= s.mode <= sc.MODE_FAST and hp.RATE_MIN_HZ <= s.rate_hz <= hp.RATE_MAX_HZ):
        failures.append("report %d: mode %d rate %d" % (n, s.mode, s.rate_hz))
    for c in s.chans:
        if c.have_cal and not (lim[0] <= c.i0 <= lim[1] and lim[2] <= c.t0 <= lim[3] and c.i0 * c.t0 <= lim[4]
                               and sc.X_STAR_MIN_OHM <= c.x <= 0 and 0 <= c.y < c.i0 * c.t0):
            failures.append("report %d: channel %d kept a calibration outside the rules: %d %d %d %d"
                            % (n, c.ch, c.i0, c.t0, c.x, c.y))
        ctl = c.ctl
        sk = (ctl.skin_rs_ohm, ctl.skin_beta_q16, ctl.skin_cp_pf)
        if sk != (0, 0, 0) and not (0 <= sk[0] <= sc.SKIN_RS_MAX_OHM and sc.SKIN_BETA_MIN_Q16 <= sk[1] <= sc.SKIN_BETA_MAX_Q16
                                    and sc.SKIN_CP_MIN_PF <= sk[2] <= sc.SKIN_CP_MAX_PF):
            failures.append("report %d: channel %d skin %r" % (n, c.ch, sk))
        if c.armed and not c.have_cal:
            failures.append("report %d: channel %d armed without a calibration" % (n, c.ch))

summary = "reports=%d pulses=%d results=%s" % (n, pulses[0], ",".join(
    ["%d:%d" % (k, results[k]) for k in sorted(results)]))
if failures:
    print("FAIL %s | %s" % (failures[0], summary))
    sys.exit(1)
print("OK " + summary)
