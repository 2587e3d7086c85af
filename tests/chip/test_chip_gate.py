"""The PIO gate on the emulated chip, driven by the real board_rp2.Board: widths
from the gate pin's edge times (emulated ns) equal T to the microsecond across the
accepted range, T outside it is refused, no word held in the state machine keeps
the gate high beyond HARD_T_MAX_US, and stop() always leaves the gate low."""

import pytest

import hid_protocol as hp

US = 1000  # ns


def window_n(cfg, t_us):
    """The samples start() says the capture keeps: its conversions, from 12 us before the rise
    to ADC_POST_US past the fall (board_rp2._CAPTURE_LEAD_US, _CAPTURE_POST_US), at most the window."""
    return min((t_us + 12 + cfg.ADC_POST_US) // cfg.ADC_SAMPLE_US, cfg.ADC_WINDOW)


def widths_us(pulses, ch=0):
    return [(p["fall_ns"] - p["rise_ns"]) / US for p in pulses if p["ch"] == ch]


def test_widths_equal_t_across_the_accepted_range(on_board, cfg):
    ts = [hp.T_FLOOR_US, hp.T_FLOOR_US + 1, 99, 100, 1000, 2047, cfg.HARD_T_MAX_US - 1, cfg.HARD_T_MAX_US]
    out = on_board.exec(f"""
b.set_amplitude(0, 1000)
b.set_amplitude(1, 1000)
ns = []
for t in {ts}:
    ns.append(b.fire(0, t))
    ns.append(b.fire(1, t))
    time.sleep_us(100)
print(ns)""")
    r = on_board.take()
    assert widths_us(r["pulses"], 0) == ts
    assert widths_us(r["pulses"], 1) == ts
    # every rise has its fall; the gate is low at the end
    assert r["gate"] == [0, 0]
    assert eval(out) == [n for t in ts for n in (window_n(cfg, t),) * 2]


@pytest.mark.parametrize("t_us", [-1, 0, 1, hp.T_FLOOR_US - 1, 8001, 65535, (1 << 30) - 1])
def test_fire_refuses_t_outside_the_range(on_board, cfg, t_us):
    """Issue 11: T = 1 used to push -1 to the PIO (0xFFFFFFFF: a gate high for 71 minutes)."""
    if t_us == 8001:
        t_us = cfg.HARD_T_MAX_US + 1
    on_board.exec("b.refused = 0")
    n = on_board.eval(f"(b.set_amplitude(0, 1000), b.fire(0, {t_us}), b.refused)[1:]")
    on_board.run(20)
    r = on_board.take()
    assert n == (0, 1) and r["edges"] == [] and r["gate"][0] == 0


@pytest.mark.parametrize("word", ["0xFFFFFFFF", "-1", "1 << 31", "0x7FFFFFFF", "0x1FFFF"])
def test_no_word_in_the_state_machine_holds_the_gate_beyond_the_hard_limit(on_board, cfg, word):
    on_board.exec(f"b.sms[0].put({word})\ntime.sleep_ms(30)")
    r = on_board.take()
    assert widths_us(r["pulses"]) == [cfg.HARD_T_MAX_US]
    assert r["gate"][0] == 0


def test_stop_mid_pulse_lowers_the_gate_at_once(on_board, cfg):
    on_board.exec("""
b.sms[0].put(5000 - 2)
time.sleep_us(1000)
t0 = time.ticks_us()
b.stop(0)
t1 = time.ticks_us()
time.sleep_ms(20)""")
    r = on_board.take()
    (p,) = r["pulses"]
    assert 1000 <= (p["fall_ns"] - p["rise_ns"]) / US < 1200  # cut, not 5000
    assert r["gate"][0] == 0


def test_stop_drops_words_still_queued_and_the_next_pulse_is_exact(on_board, cfg):
    on_board.exec("""
sm = b.sms[0]
for w in (3000, 3000, 3000, 3000):
    sm.put(w)
time.sleep_us(500)
b.stop(0)
time.sleep_ms(20)""")
    r = on_board.take()
    assert len(r["pulses"]) == 1 and r["gate"][0] == 0  # the queued words never fired
    on_board.exec("b.set_amplitude(0, 1000)\nb.fire(0, 700)\ntime.sleep_ms(2)")
    assert widths_us(on_board.take()["pulses"]) == [700]


def test_stop_when_idle_or_twice_keeps_the_gate_low_without_a_glitch(on_board, cfg):
    on_board.exec("b.stop(0)\nb.stop(0)\nb.stop_all()\ntime.sleep_ms(5)")
    r = on_board.take()
    assert r["edges"] == [] and r["gate"] == [0, 0]


def test_the_board_calls_of_the_frame_allocate_nothing(on_board, cfg):
    """fire (accepted and refused), stop, set_amplitude and feed_watchdog under the heap lock."""
    out = on_board.exec("""
b.refused = 0
micropython.heap_lock()
try:
    for t in (100, 1000, 5, 9000):
        b.set_amplitude(0, 1500)
        b.fire(0, t)
        b.stop(0)
        b.feed_watchdog()
    ok = 1
except MemoryError:
    ok = 0
micropython.heap_unlock()
print(ok, b.refused)""")
    assert out.split() == ["1", "2"]
    assert widths_us(on_board.take()["pulses"]) == [100, 1000]


def test_a_t_outside_the_range_that_gets_past_the_firmware_is_refused_by_the_board(on_board, cfg):
    """Defence in depth: the board's own check refuses T outside [T_FLOOR_US, HARD_T_MAX_US]
    when called directly (the firmware's checks bypassed), and the firmware's last check
    latches a channel whose state holds T = 5 us without calling the board at all."""
    on_board.load(0, rp_ohm=10000)
    out = on_board.exec("""
b.refused = 0
s = stim.Stimulator(b, board_rp2.Clock(), cfg, 1, 50)
buf = bytearray(hp.REPORT_LEN)
for rep in (hp.cmd_calibrate(buf, hp.CH_ALL, 1000, 1000, -1670, 186000), hp.cmd_arm(bytearray(64), hp.CH_ALL)):
    assert s.handle(rep, time.ticks_us()) == hp.RES_OK
s.sync_outputs()
s.run(2)
n = [b.fire(0, t) for t in (5, hp.T_FLOOR_US - 1, 0, -1, cfg.HARD_T_MAX_US + 1)]
direct = b.refused
c = s.chans[0]
c.held = False
c.t = 5
s.run(3)
print(sum(n), direct, b.refused, c.armed, c.stop == hp.STOP_LIMIT)""")
    r = on_board.take()
    assert out.split() == ["0", "5", "5", "False", "True"]
    assert all(w >= hp.T_FLOOR_US for w in widths_us(r["pulses"])) and len(r["pulses"]) == 2
    assert r["gate"][0] == 0


def test_start_returns_while_the_pulse_runs_and_wait_ends_its_capture(on_board, cfg):
    """start() hands the pulse to PIO + DMA and returns at once (the gate still high),
    wait() returns after the capture (gate low, DMA idle, ADC stopped); both allocate
    nothing; stopping the captured channel mid-pulse ends the capture at once, and
    stopping another channel leaves the running pulse and its capture alone."""
    out = on_board.exec("""
import rp2
b.set_amplitude(0, 1000)
b.set_amplitude(1, 1000)
st = [0] * 10  # filled under the heap lock (a tuple would allocate)
def look(k):
    st[k] = time.ticks_us()  # (rp2040js does not show a PIO-driven pin in SIO GPIO_IN: edges come from the host)
    st[k + 1] = 1 if b.dma.active() else 0
    st[k + 2] = b.capturing
micropython.heap_lock()
try:
    st[9] = b.start(0, 2000)
    time.sleep_us(300)
    look(0)
    b.stop(1)  # another channel: this pulse goes on
    b.wait()
    look(3)
    b.start(0, 3000)
    time.sleep_us(500)
    b.stop(0)  # mid-pulse, its capture running
    look(6)
    ok = 1
except MemoryError:
    ok = 0
micropython.heap_unlock()
print((ok, st, machine.mem32[0x4004C000] & 0x8))""")
    ok, st, adc_running = eval(out)
    n, mid, end, cut = st[9], tuple(st[0:3]), tuple(st[3:6]), tuple(st[6:9])
    r = on_board.take()
    assert ok == 1 and n == window_n(cfg, 2000)
    assert mid[1:] == (1, 0) and end[1:] == (0, -1) and cut[1:] == (0, -1) and adc_running == 0
    # the CPU ran on 300 us into the 2 ms pulse (capture still running), wait() returned after its end
    assert 1500 <= end[0] - mid[0] <= 2100
    w = widths_us(r["pulses"])
    assert w[0] == 2000 and 500 <= w[1] < 3000 and r["gate"][0] == 0
