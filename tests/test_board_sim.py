"""The simulated board's analog path (firmware/board_sim.py): the realistic errors
it claims (docs/simulation.md, "The realistic board") and the ideal switch."""

import math
import statistics
import sys

import pytest

from conftest import FIRMWARE, SHARED

sys.path[:0] = [str(FIRMWARE), str(SHARED)]
import board_config as cfg  # noqa: E402
import board_sim  # noqa: E402
import sim_electrode  # noqa: E402


def board(ideal=False, load_ohm=0, correction=None, noise=None, seed=3):
    return board_sim.SimBoard(cfg, board_sim.VirtualClock(), sim_electrode.scenario("steady"), 2, seed,
                              ideal=ideal, load_ohm=load_ohm, correction=correction, noise_counts=noise)


@pytest.mark.parametrize("i_ua", [0, 1, 2, 3, 500, 999, 1000, 1001, 2670, 4096, 9997, 9998, 9999, 10000])
def test_set_amplitude_returns_code_times_lsb_never_above_the_command(i_ua):
    b = board()
    got = b.set_amplitude(0, i_ua)
    code = min(i_ua * 4096 // cfg.AMP_UA_AT_FULL, 4095)
    assert got == -(-code * cfg.AMP_UA_AT_FULL // 4096)  # whole uA, rounded up (dac_mcp4822.ua_for)
    assert 0 <= i_ua - got <= math.ceil(cfg.AMP_UA_AT_FULL / 4096) or i_ua >= 9998
    assert board(ideal=True).set_amplitude(0, i_ua) == i_ua


def test_dac_steps_are_at_most_2_5_ua():
    b = board()
    codes = sorted({b.analog.code(i) for i in range(0, 10001)})
    assert codes == list(range(4096))  # every code reachable: steps of one LSB
    assert cfg.AMP_UA_AT_FULL / 4096 <= 2.5
    for i in range(0, 10001, 7):  # reported: code x LSB in whole uA (rounded up: never below it)
        assert 0 <= b.set_amplitude(0, i) - b.analog.code(i) * cfg.AMP_UA_AT_FULL / 4096 < 1


def test_the_dac_settles_first_order_in_its_datasheet_time():
    b = board()
    b.set_amplitude(0, 1000)
    b.clock.advance(20000)
    b.set_amplitude(0, 3000)
    target = b.analog.physical_ua(0, b.code[0])
    start = b.analog.physical_ua(0, b.analog.code(1000))
    assert abs(b._level_ua(0, 0) - start) < 1e-9
    half_lsb = cfg.AMP_UA_AT_FULL / 4096 / 2
    assert abs(b._level_ua(0, board_sim.DAC_SETTLE_US) - target) <= half_lsb * 1.01
    assert abs(b._level_ua(0, board_sim.DAC_SETTLE_US / 2) - target) > half_lsb


def _pulse_counts(b, ch, i_ua, t_us):
    """The samples of the window taken while the gate was high."""
    b.set_amplitude(ch, i_ua)
    b.clock.advance(20000)
    b.fire(ch, t_us)
    return list(b.adc[ch][b.last_rise[ch]:b.last_edge[ch]])


def test_adc_noise_is_the_datasheet_enob_and_the_ideal_board_keeps_1_5_counts():
    for ideal, sigma in ((False, 2.84), (True, 1.5)):
        b = board(ideal=ideal, load_ohm=10000)
        xs = []
        for _ in range(40):
            xs += _pulse_counts(b, 0, 1700, 2000)  # ~17 V, ~620 counts: away from the DNL codes
        assert abs(statistics.pstdev(xs) - sigma) < 0.12 * sigma, (ideal, statistics.pstdev(xs))


def test_e11_dnl_codes_are_wide_and_their_neighbours_missing():
    b = board(noise=3.0, load_ohm=10000)
    seen = {}
    # sweep the input through 512 counts (13.8 V at 27 mV/count): 1.30 .. 1.44 mA on 10 kohm
    for i in range(1300, 1440, 2):
        for c in _pulse_counts(b, 0, i, 400):
            seen[c] = seen.get(c, 0) + 1
    h = board_sim.ADC_DNL_WIDTH // 2
    assert seen.get(512, 0) > 4 * max(seen.get(c, 0) for c in (500, 501, 523, 524))
    for c in list(range(512 - h, 512)) + list(range(513, 513 + h)):
        assert c not in seen
    ideal = board(ideal=True, load_ohm=10000)
    seen_i = set()
    for i in range(1300, 1440, 2):
        seen_i.update(_pulse_counts(ideal, 0, i, 400))
    assert set(range(512 - h, 513 + h)) <= seen_i


def test_monitor_gain_and_offset_error_per_channel_and_compliance_clipping():
    b = board(noise=0.0, load_ohm=10000)
    for ch in (0, 1):
        counts = _pulse_counts(b, ch, 4000, 500)
        i_phys = b.analog.physical_ua(ch, b.analog.code(4000))
        v_mv = i_phys * 10.0  # uA x 10 kohm = mV
        want = v_mv * board_sim.MON_GAIN[ch] * 1000 / cfg.VMON_UV_PER_COUNT + board_sim.MON_OFFSET_MV[ch] * 1000 / cfg.VMON_UV_PER_COUNT
        assert abs(counts[-1] - want) <= 1
    b = board(noise=0.0, load_ohm=20000)
    clipped = _pulse_counts(b, 0, 6000, 500)  # 120 V on 20 kohm: clipped at the 100 V compliance
    full = cfg.COMPLIANCE_MV * board_sim.MON_GAIN[0] * 1000 / cfg.VMON_UV_PER_COUNT
    assert abs(max(clipped) - (full + board_sim.MON_OFFSET_MV[0] * 1000 / cfg.VMON_UV_PER_COUNT)) <= 1
    assert abs(b.last_i_ua[0] - cfg.COMPLIANCE_MV / 20.0) < 1e-6  # the current a clipped output really drives


# the stored correction taking out gain and offset: tests/test_vmon_cal.py (stim._measure applies it)


def test_correction_integers_stay_below_2_30_at_the_accepted_extremes():
    for gppm in board_sim.CAL_GAIN_PPM:
        for off in board_sim.CAL_OFFSET_MV:
            k, o = board_sim.correction_terms(gppm, off, cfg.VMON_UV_PER_COUNT)
            for c in (0, board_sim.ADC_MAX):
                assert abs((c * 16 - o) * k + 65536) < 2**30
                assert 0 <= board_sim.correct_count(c, k, o) <= board_sim.ADC_MAX


@pytest.mark.parametrize("text, words", [
    ("", "first line"),
    (board_sim.CAL_HEADER + "\n0 1000000\n", "line 2"),
    (board_sim.CAL_HEADER + "\n0 2000000 0\n", "out of range"),
    (board_sim.CAL_HEADER + "\n0 1000000 5000\n", "out of range"),
])
def test_a_bad_correction_file_is_refused_naming_the_line(text, words):
    with pytest.raises(ValueError, match=words):
        board_sim.parse_correction(text, 2)


@pytest.mark.parametrize("t_us", [20, 21, 33, 99, 100, 101, 333, 1000, 2001, 8000])
def test_the_capture_is_the_chips_window_with_the_falling_edge_in_it(t_us):
    """As board_rp2 on the chip (tests/chip/test_chip_adc.py): the last min((T + 12 + ADC_POST_US) // 2,
    ADC_WINDOW) conversions 2 us apart, the falling edge among them with the last conversion before it
    in the pulse's last 2 us and ADC_POST_US of the decay after it; on a resistor, the samples in the
    pulse read the load and the ones after the fall read nothing (no current)."""
    b = board(ideal=True, load_ohm=10000, noise=0.0)
    for lead in (13.0, 13.7, 14.99, None):
        b.lead_us = lead
        b.set_amplitude(0, 1000)
        b.clock.advance(20000)
        n = b.fire(0, t_us)
        w = cfg.ADC_WINDOW
        span = t_us + 12 + cfg.ADC_POST_US
        assert n == min(span // cfg.ADC_SAMPLE_US, w)
        rise, edge = b.last_rise[0], b.last_edge[0]
        assert w - n <= rise < edge < w and w - edge >= (cfg.ADC_POST_US - 4) // cfg.ADC_SAMPLE_US  # the decay after it
        first_t = span // cfg.ADC_SAMPLE_US * cfg.ADC_SAMPLE_US - n * cfg.ADC_SAMPLE_US  # from the ADC start
        if lead is not None:
            t_last = first_t + (edge - 1 - (w - n)) * cfg.ADC_SAMPLE_US - lead  # from the rise
            assert t_us - cfg.ADC_SAMPLE_US <= t_last < t_us
        v = list(b.adc[0])
        level = round(1000 * 10000 / cfg.VMON_UV_PER_COUNT)  # 10 V in counts
        assert v[rise:edge] == [level] * (edge - rise)
        assert v[edge:] == [0] * (w - edge) and v[w - n:rise] == [0] * (rise - w + n)


def test_the_firmware_read_of_an_electrode_is_its_end_of_pulse_rp_within_the_last_4_us():
    """The pair-min of the window (stim._peak_counts' rule) on an Rs + (Rp || C) electrode,
    no noise: between the model 4 us before the end and the model at the end, within a count."""
    e = sim_electrode.Electrode()
    b = board_sim.SimBoard(cfg, board_sim.VirtualClock(), sim_electrode.scenario("steady"), 1, 3,
                           electrodes=[e], ideal=True, noise_counts=0.0)
    for t_us in (20, 100, 101, 1000):
        b.set_amplitude(0, 1000)
        b.clock.advance(20000)
        n = b.fire(0, t_us)
        v = list(b.adc[0])[cfg.ADC_WINDOW - n:]
        got_mv = max(min(x, y) for x, y in zip(v, v[1:])) * cfg.VMON_UV_PER_COUNT / 1000
        end_mv = 1000 / 1000 * (e.rs + e.rp_skin * (1 - math.exp(-t_us / e.tau))) * 1000
        early_mv = 1000 / 1000 * (e.rs + e.rp_skin * (1 - math.exp(-(t_us - 4) / e.tau))) * 1000
        count_mv = cfg.VMON_UV_PER_COUNT / 1000
        assert early_mv - count_mv <= got_mv <= end_mv + count_mv, (t_us, got_mv, early_mv, end_mv)


def test_a_held_scenario_stays_at_its_time_0_until_the_host_starts_it():
    """SimBoard.held (main.py --hold, what sim:// runs in real time): the world is the scenario's
    state at time 0 however long the board runs; SIM_START (board.sim) starts its clock then."""
    scen = sim_electrode.Scenario("t", [(0.0, 0.6, 1.0, 0.0), (1.0, 0.0, 0.5, 0.0)], 1.0, interp_h=True)
    b = board_sim.SimBoard(cfg, board_sim.VirtualClock(), scen, 1, 3)
    b.held = True
    for _ in range(100):  # 2 s of frames
        b.clock.advance(20000)
        b.feed_watchdog()
    e = b.electrodes[0]
    assert b.t_s == 0.0 and e.contact == 0.6 and e.h == 1.0
    b.sim(board_sim.SIM_START + 1)  # not a start: nothing
    b.clock.advance(20000)
    b.feed_watchdog()
    assert b.held and b.t_s == 0.0
    b.sim(board_sim.SIM_START)
    b.clock.advance(250000)
    b.feed_watchdog()
    assert not b.held and b.t_s == 0.25 and abs(e.contact - 0.45) < 1e-12 and abs(e.h - 0.875) < 1e-12
    b.sim(board_sim.SIM_START)  # once running, a second start changes nothing
    b.clock.advance(250000)
    b.feed_watchdog()
    assert b.t_s == 0.5


def _reports(out, want, timeout_s=60.0):
    """Read framed reports from the VM's stdout until `want` says stop or it ends; (reports, ended)."""
    import os
    import select
    import time

    reps, buf = [], b""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not want(reps):
        if not select.select([out], [], [], 1.0)[0]:
            continue
        chunk = os.read(out.fileno(), 65536)
        if not chunk:
            return reps, True
        buf += chunk
        while len(buf) >= 66:
            assert buf[:2] == bytes((board_sim.MAGIC0, board_sim.MAGIC1))
            reps.append(buf[2:66])
            buf = buf[66:]
    return reps, False


def test_a_held_vm_runs_its_frames_only_after_the_host_starts_its_scenario(micropython):
    """main.py --realtime --hold --frames 10: the device runs, reports and counts no frame until
    the SIM_START message arrives on stdin (here after 30 frames: however long a host waits),
    then runs its 10 frames and exits 0. The message is for the simulated world: the firmware
    answers nothing to it. Without --realtime, --hold is refused in one line."""
    import subprocess

    import hid_protocol as hp

    from conftest import SHARED

    env = {"MICROPYPATH": f"{SHARED}:{FIRMWARE}"}
    args = [micropython, str(FIRMWARE / "main.py"), "--scenario", "steady", "--channels", "1", "--frames", "10",
            "--auto", "1000,1000,-1670,186000", "--exit-on-eof"]
    p = subprocess.Popen(args + ["--realtime", "--hold"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, env=env)
    try:
        tel = lambda reps: [r for r in reps if r[0] == hp.REP_TELEMETRY]  # noqa: E731
        before, ended = _reports(p.stdout, lambda reps: len(tel(reps)) >= 30)
        assert not ended and len(tel(before)) >= 30, (len(tel(before)), p.stderr.read())
        p.stdin.write(bytes((board_sim.MAGIC0, board_sim.MAGIC_SIM, board_sim.SIM_START)) + bytes(63))
        p.stdin.flush()
        after, ended = _reports(p.stdout, lambda reps: False)
        assert ended and p.wait(timeout=30) == 0
    finally:
        p.kill() if p.poll() is None else None
    assert 10 <= len(tel(after)) == len(after)  # its 10 frames after the start, and no answer to the message
    seq = [int.from_bytes(r[hp.O_SEQ:hp.O_SEQ + 4], "little") for r in tel(before + after)]
    assert seq == list(range(seq[0], seq[0] + len(seq)))  # one stream: nothing lost around the message
    r = subprocess.run(args + ["--hold"], capture_output=True, env=env, timeout=60)
    assert r.returncode == 2 and r.stderr.decode().strip() == "steadytouch firmware: --hold needs --realtime " \
        "(a host starts the scenario in its own time)", r.stderr
