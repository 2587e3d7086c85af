"""The hid:// transport against a fake hidapi module with cython-hidapi's API."""

import pytest

import hid_protocol as hp
from steadytouch.device import Device, DeviceError
from steadytouch.protocol import Telemetry
from steadytouch.transport import Disconnected, HidTransport, TransportError, open_transport


def telemetry_report(seq, ch=0):
    b = bytearray(64)
    b[0] = hp.REP_TELEMETRY
    b[1] = ch
    hp.put_i32(b, hp.O_SEQ, seq)
    hp.put_u16(b, hp.O_I, 1000)
    return list(b)


class FakeHidDevice:
    def __init__(self, script):
        self.script = list(script)  # what read() returns, in order: list of ints, [], or an exception
        self.written = []
        self.opened = None
        self.closed = False
        self.answer_acks = True

    def open(self, vid, pid, serial=None):
        self.opened = (vid, pid, serial)

    def read(self, n, timeout_ms=0):
        assert n == 64 and timeout_ms >= 1
        if not self.script:
            return []
        item = self.script.pop(0)
        if isinstance(item, Exception):
            raise item
        return item

    def write(self, data):
        data = bytes(data)
        self.written.append(data)
        if self.answer_acks and len(data) == 65:
            ack = bytearray(64)
            ack[0] = hp.REP_ACK
            ack[hp.O_CMD] = data[1]
            ack[hp.O_TAG] = data[2]
            ack[hp.O_RESULT] = hp.RES_OK if data[1] != hp.CMD_ARM else hp.RES_NOT_CALIBRATED
            hp.put_i32(ack, hp.O_SEQ, 99)
            self.script.insert(0, list(ack))
        return len(data)

    def close(self):
        self.closed = True


class FakeHid:
    def __init__(self, dev, present=True, open_error=None):
        self.dev = dev
        self.present = present
        self.open_error = open_error

    def enumerate(self, vid=0, pid=0):
        if not self.present:
            return []
        return [{"vendor_id": vid, "product_id": pid, "serial_number": "ABC", "product_string": "steadytouch"}]

    def device(self):
        if self.open_error:
            err = self.open_error

            class Broken(FakeHidDevice):
                def open(self, *a):
                    raise err

            return Broken([])
        return self.dev


def test_reads_reports_and_times_out():
    dev = FakeHidDevice([telemetry_report(1), [], telemetry_report(2)])
    t = HidTransport(hp.VID, hp.PID, hid_module=FakeHid(dev))
    assert dev.opened == (hp.VID, hp.PID, None)
    assert t.read(0.1)[0] == hp.REP_TELEMETRY
    assert t.read(0.1) is None  # timeout
    assert len(t.read(0.1)) == 64
    t.close()
    assert dev.closed


def test_writes_carry_the_report_id_byte():
    dev = FakeHidDevice([])
    t = HidTransport(hp.VID, hp.PID, hid_module=FakeHid(dev))
    report = bytes(hp.cmd_get_info(bytearray(64), 7))
    t.write(report)
    assert dev.written == [b"\x00" + report]


def test_disconnect_mid_stream_is_a_clear_error():
    dev = FakeHidDevice([telemetry_report(1), OSError("read error")])
    t = HidTransport(hp.VID, hp.PID, hid_module=FakeHid(dev))
    d = Device(t)
    assert isinstance(d.read(0.1), Telemetry)
    with pytest.raises(Disconnected, match="went away"):
        d.read(0.1)


def test_short_report_is_a_disconnect():
    dev = FakeHidDevice([[1, 2, 3]])
    t = HidTransport(hp.VID, hp.PID, hid_module=FakeHid(dev))
    with pytest.raises(Disconnected, match="3-byte report"):
        t.read(0.1)


def test_no_device_and_permission_denied_say_what_to_do():
    with pytest.raises(TransportError, match="steadytouch devices"):
        HidTransport(hp.VID, hp.PID, hid_module=FakeHid(None, present=False))
    with pytest.raises(TransportError, match="70-steadytouch.rules"):
        HidTransport(hp.VID, hp.PID, hid_module=FakeHid(None, open_error=OSError("open failed")))


def test_url_parsing_and_serial():
    dev = FakeHidDevice([])
    t = open_transport("hid://1209:0001/ABC", hid_module=FakeHid(dev))
    assert t.url == "hid://1209:0001/ABC" and dev.opened == (0x1209, 1, "ABC")
    with pytest.raises(TransportError, match="hid://VID:PID"):
        open_transport("hid://zz:1", hid_module=FakeHid(dev))
    with pytest.raises(TransportError, match="sim://SCENARIO"):
        open_transport("tcp://localhost")


def test_commands_wait_for_their_ack_and_count_gaps():
    dev = FakeHidDevice([telemetry_report(1), telemetry_report(5)])
    d = Device(HidTransport(hp.VID, hp.PID, hid_module=FakeHid(dev)))
    assert d.keepalive(1000).ok
    assert isinstance(d.read(0.1), Telemetry) and isinstance(d.read(0.1), Telemetry)
    assert d.lost > 0  # 1 -> 5 after the ack's seq: gaps counted
    with pytest.raises(DeviceError, match="arm: not calibrated"):
        d.arm()
    dev.answer_acks = False
    with pytest.raises(DeviceError, match="no answer to 'disarm' within 0.3 s"):
        d.command(d.cmds.disarm(), timeout_s=0.3)
