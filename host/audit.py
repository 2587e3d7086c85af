"""Audit a recording: replay every recorded pulse through sensation_core on
CPython (the host reference of the device's own integer law) from the recorded
calibration and Rp, and list every pulse where the device chose a different
next I or T. Expected: none — the same integer code runs on both."""

from __future__ import annotations

from dataclasses import dataclass

import decay
import hid_protocol as hp
import sensation_core as sc

from .record import RecordingError, meta_int


AUDIT_COLUMNS = ("mode", "flags", "stop", "next_i_ua", "next_t_us")
SENT_STATUS_FIRMWARE = (0, 4, 0)  # the first firmware that reports the status of the pulse sent (telemetry sent_status)
SKIN_FIRMWARE = (0, 4, 1)  # the first whose `record` header holds each channel's skin model (GET_INFO's Calibration)
SKIN_KEYS = ("skin_rs_ohm", "skin_beta_q16", "skin_cp_pf", "skin_tau_q16")  # (the last: firmware 0.5.0 on, optional)
TAU_FIRMWARE = (0, 5, 0)  # the first whose controller reads the decay's tau (ltau_q16: 0.4.0 reported it, unused)


def _firmware(meta: dict, path) -> tuple | None:
    """The header's firmware version as a tuple (None: not in the header)."""
    v = meta.get("firmware")
    if v is None:
        return None
    try:
        return tuple(int(x) for x in v.split("."))
    except ValueError:
        raise RecordingError(f"{path}: metadata 'firmware' is not a version like 0.4.0: {v!r}") from None


@dataclass
class Mismatch:
    line: int  # data row number, 1-based
    seq: int
    channel: int
    expected: tuple[int, int]
    recorded: tuple[int, int]


@dataclass
class AuditResult:
    checked: int
    mismatches: list[Mismatch]
    skipped: int  # pulses before the replay had a calibration (or on a channel the header does not calibrate)
    no_skin: bool = False  # MODE_FAST pulses replayed on a channel whose header has no skin model (an older firmware)


def audit(meta: dict, rows: list[dict], path="recording") -> AuditResult:
    lim = [meta_int(meta, k, path) for k in ("i_min_ua", "i_max_ua", "t_min_us", "t_max_us", "q_max_pc")]
    try:
        sc.Controller(*lim)
    except ValueError as e:
        raise RecordingError(f"{path}: limits in the header are not valid: {e}") from None
    missing = [k for k in AUDIT_COLUMNS if k not in rows[0]]
    if missing:
        raise RecordingError(f"{path}: cannot audit without the column(s) {', '.join(missing)}")
    # the status of each pulse sent (its bounds, told to the controller before its update): from firmware 0.4.0
    # on; a device before it sends none (the host records 0s: ignored), its controller kept its own status
    fw = _firmware(meta, path)
    sent = "sent_status" in rows[0] and (fw is None or fw >= SENT_STATUS_FIRMWARE)
    if fw is not None and fw >= SENT_STATUS_FIRMWARE and not sent:
        raise RecordingError(f"{path}: firmware {meta['firmware']} reports the status of each pulse sent; "
                             "cannot audit without the column sent_status")
    # the decay's log2 tau after each pulse, told to the controller before its update: from firmware 0.5.0 on
    # (0.4.0 reported it in telemetry but its controller did not read it: the replay tells it none)
    tau = "ltau_q16" in rows[0] and (fw is None or fw >= TAU_FIRMWARE)
    if fw is not None and fw >= TAU_FIRMWARE and not tau:
        raise RecordingError(f"{path}: firmware {meta['firmware']}'s controller reads the decay after each pulse; "
                             "cannot audit without the column ltau_q16")
    ctls: dict[int, sc.Controller] = {}
    cals: dict[int, tuple] = {}
    used: set[str] = set()  # the skin model keys a calibration took
    for ch in range(4):
        if f"ch{ch}_i0_ua" in meta:
            cal = tuple(meta_int(meta, f"ch{ch}_{k}", path) for k in ("i0_ua", "t0_us", "x_star_ohm", "y_star_pc"))
            cals[ch] = cal
            c = sc.Controller(*lim)
            used |= _skin(c, meta, f"ch{ch}_", path, fw)
            rp0 = int(meta.get(f"ch{ch}_rp0_ohm", "0") or 0)
            if rp0:
                c.calibrate(cal[0], cal[1], rp0, cal[2], cal[3])
            ctls[ch] = c
    if not cals and "i0_ua" in meta:  # one calibration for all channels
        cal = tuple(meta_int(meta, k, path) for k in ("i0_ua", "t0_us", "x_star_ohm", "y_star_pc"))
        for ch in range(4):
            cals[ch] = cal
            ctls[ch] = sc.Controller(*lim)
            used |= _skin(ctls[ch], meta, "", path, fw)
    if not cals:
        raise RecordingError(f"{path}: no calibration (i0_ua, t0_us, x_star_ohm, y_star_pc) in the header")
    stray = sorted(k for k in meta if k.endswith(SKIN_KEYS) and k not in used)
    if stray:  # (a hand-made header: a model the replay would silently leave out)
        raise RecordingError(f"{path}: skin model key(s) {', '.join(stray)} belong to no calibration in the header "
                             "(per channel: ch<n>_skin_* beside ch<n>_i0_ua; one for all: skin_* beside i0_ua)")
    try:
        r = _replay(rows, ctls, cals, sent, tau)
    except ValueError as e:  # a recorded value the core refuses (mode, limits, calibration)
        raise RecordingError(f"{path}: {e}") from None
    # MODE_FAST replayed with no model where the header could not say which (firmware before 0.4.1)
    r.no_skin = (fw is None or fw < SKIN_FIRMWARE) and any(
        row["mode"] == sc.MODE_FAST and row["channel"] in ctls
        and f"ch{row['channel']}_{SKIN_KEYS[0]}" not in meta and SKIN_KEYS[0] not in meta for row in rows)
    return r


def _skin(c, meta, prefix, path, fw=None):
    """MODE_FAST's skin model from the header (`record`: GET_INFO's Calibration report, firmware 0.4.1 on),
    as the device's controller had it; none in the header: none (0 0 0). Returns the keys it took."""
    keys = [prefix + k for k in SKIN_KEYS[:3]]
    have = [k for k in keys if k in meta]
    if not have:
        return set()
    if len(have) < len(keys):
        raise RecordingError(f"{path}: the skin model in the header lacks {', '.join(k for k in keys if k not in meta)}")
    v = [meta_int(meta, k, path) for k in keys]
    tk = prefix + SKIN_KEYS[3]  # rule 7's tau gain (a header before firmware 0.5.0 has none: off)
    if tk not in meta and fw is not None and fw >= TAU_FIRMWARE:  # (review of session 26: replayed with tau off,
        # the device blamed for the mismatches)
        raise RecordingError(f"{path}: the skin model in the header lacks {tk} (firmware {meta['firmware']} "
                             "records rule 7's tau gain beside the model)")
    if tk in meta:
        keys.append(tk)
        v.append(meta_int(meta, tk, path))
        if not any(v[:3]) and v[3] != sc.SKIN_TAU_OFF:
            raise RecordingError(f"{path}: {tk}={v[3]} with no skin model (a tau gain goes with a model; off: "
                                 f"{sc.SKIN_TAU_OFF})")
    try:
        c.set_skin(*v)
    except ValueError as e:
        raise RecordingError(f"{path}: the skin model in the header is not valid: {e}") from None
    return set(keys)


def _replay(rows, ctls, cals, sent, tau) -> AuditResult:
    checked, skipped, bad = 0, 0, []
    cal_rp = dict.fromkeys(ctls, 0)  # per channel: the last calibration pulse's Rp not yet confirmed
    cal_pair = {}  # per channel: the two readings that gave Rp0 (a mode change while armed takes it again)
    for n, r in enumerate(rows, start=1):
        ch = r["channel"]  # one of the recording's channels (read_recording refuses any other)
        if r["i_ua"] == 0:
            if ch in cal_rp:
                cal_rp[ch] = 0  # (a frame without a pulse: stopped; ARM starts the calibration again)
            continue  # no pulse this frame
        if ch not in ctls:  # a channel the header gives no calibration for
            skipped += 1
            continue
        try:
            done = _step(ctls[ch], r, cals[ch], cal_rp, cal_pair, ch, sent, tau)
        except ValueError as e:
            raise ValueError(f"data row {n}: {e}") from None
        if not done:
            skipped += 1
            continue
        checked += 1
        c = ctls[ch]
        exp = (c.i_ua, c.t_us)
        got = (r["next_i_ua"], r["next_t_us"])
        if exp != got:
            bad.append(Mismatch(n, r["seq"], ch, exp, got))
    return AuditResult(checked, bad, skipped)


def _ltau(r, tau) -> int:
    """The row's log2 tau as the device told its controller (0: none, or a firmware that told none)."""
    lt = r["ltau_q16"] if tau else 0
    if not 0 <= lt < decay.LTAU_END:
        raise ValueError(f"ltau_q16={lt} out of range 0..{decay.LTAU_END - 1}")
    return lt


def _step(c, r, cal, cal_rp, cal_pair, ch, sent, tau) -> bool:
    """Replay one recorded pulse on controller c; False if it cannot be (no calibration yet).
    cal_rp[ch]: the channel's last calibration pulse's Rp not yet confirmed (0: none);
    cal_pair[ch]: the two readings that gave its Rp0 (the device's stim SET_MODE takes Rp0 again
    from them, for the new mode, when the mode changes while the channel is armed)."""
    # a mode change while armed: Rp0 again for the new law (FLAG_MODE_SET, firmware 0.4.0 on: also two SET_MODEs
    # between two reports that end in the mode before, FAST -> X -> FAST, which calibrate it again all the same)
    changed = r["mode"] != c.mode or r["flags"] & hp.FLAG_MODE_SET
    if not r["flags"] & hp.FLAG_CALIBRATING and c.calibrated and changed and ch in cal_pair:
        i0, t0, x, y = cal
        c.calibrate(i0, t0, hp.cal_rp0(*cal_pair[ch], r["mode"] == sc.MODE_CONSTANT_ENERGY), x, y)
    c.set_mode(r["mode"])
    if r["flags"] & hp.FLAG_CALIBRATING:  # (the device's stim._control: Rp0 once two readings agree)
        i0, t0, x, y = cal
        rp = r["rp_ohm"]
        r1 = cal_rp[ch]  # the calibration pulse before this one, since arming
        cal_rp[ch] = 0
        if sc.RP_MIN_OHM <= rp <= sc.RP_MAX_OHM and r["stop"] != hp.STOP_ELECTRODE_OFF:
            rp0 = hp.cal_rp0(r1, rp, r["mode"] == sc.MODE_CONSTANT_ENERGY)
            if rp0:
                c.ltau_q16 = _ltau(r, tau)  # (the device tells calibrate the calibration pulse's tau: rule 7)
                c.calibrate(i0, t0, rp0, x, y)
                cal_pair[ch] = (min(r1, rp), max(r1, rp))
            elif r["stop"] == hp.STOP_RP_FAULT:  # readings that never agreed: latched
                c.stop(sc.ST_UNCALIBRATED)
            else:  # the calibration pulse again
                cal_rp[ch] = rp
                c.delivered(i0, t0, c.status)  # (the device leaves the status as it is)
        else:
            c.stop(sc.ST_RP_LOW if rp < sc.RP_MIN_OHM else sc.ST_RP_HIGH)
    elif not c.calibrated:
        cal_rp[ch] = 0
        return False
    elif r["stop"] == hp.STOP_ELECTRODE_OFF:
        c.stop(sc.ST_RP_HIGH)  # the supervisor's stop: Vp at compliance or Rp above range
    else:
        for name, hi in (("i_ua", sc.I_LIMIT_UA), ("t_us", sc.T_LIMIT_US)):  # (a device never reports past them)
            if not 0 <= r[name] <= hi:
                raise ValueError(f"{name}={r[name]} out of range 0..{hi}")
        # the bounds of the pulse sent, as the device tells its controller (a recording before firmware 0.4.0
        # has no sent_status: its firmware left the controller's own status, and so does the replay)
        st = r["sent_status"] if sent else c.status
        if st & ~sc.ST_BOUND_MASK or st < 0:
            raise ValueError(f"sent_status={st} out of range (bits of 0x{sc.ST_BOUND_MASK:x})")
        c.delivered(r["i_ua"], r["t_us"], st)
        c.ltau_q16 = _ltau(r, tau)  # (the device's stim._control: the decay read after the pulse, for this update)
        c.update(r["rp_ohm"])
    return True
