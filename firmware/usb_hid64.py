# A vendor-defined USB HID interface with 64-byte interrupt IN and OUT
# endpoints, on micropython-lib's usb-device-hid (`steadytouch flash` installs
# the pinned usb-device 0.2.1 + usb-device-hid 0.1.2; its stock HIDInterface has
# one 8-byte IN endpoint only). IN reports are copied into a ring of slots and
# sent one at a time; OUT reports land in a ring that the frame polls.
#
# Works with usb-device-hid 0.1.2 and 0.2.0: the endpoint descriptors and their
# polling interval are our own (0.1.2 has no interval argument, 0.2.0 names it
# interval_ms), so only arguments both versions take go to HIDInterface.
from micropython import const

from usb.device.hid import HIDInterface

import hid_protocol as hp

_EP_IN_FLAG = const(0x80)
_SLOTS = const(16)
INTERVAL_MS = const(1)  # bInterval of both interrupt endpoints (full speed: ms)

# what this module uses of the library; a version without it is refused by name
for _name in ("get_hid_descriptor", "submit_xfer", "xfer_pending", "is_open", "on_open", "on_set_report"):
    if not hasattr(HIDInterface, _name):
        raise ImportError("usb-device-hid on the board has no HIDInterface.%s: steadytouch needs usb-device-hid "
                          "0.1.2 (pinned) or 0.2.0; run `steadytouch flash` to install the pinned version" % _name)


class Hid64(HIDInterface):
    def __init__(self):
        # no interval argument: usb-device-hid 0.1.2 has none, 0.2.0 has interval_ms;
        # this class writes its own endpoint descriptors with INTERVAL_MS
        super().__init__(hp.REPORT_DESCRIPTOR, set_report_buf=bytearray(hp.REPORT_LEN),
                         interface_str="steadytouch")
        self._out_ep = None
        self._rx_xfer = bytearray(hp.REPORT_LEN)
        self._rx = [bytearray(hp.REPORT_LEN) for _ in range(_SLOTS)]
        self._rx_head = 0
        self._rx_tail = 0
        self._tx = [bytearray(hp.REPORT_LEN) for _ in range(_SLOTS)]
        self._tx_head = 0
        self._tx_tail = 0
        self.dropped = 0  # IN reports dropped because the host did not read (gaps in seq)
        self._tx_done_cb = self._tx_done  # bound once: no allocation per transfer
        self._rx_done_cb = self._rx_done

    # ---- descriptors: one interface, interrupt IN and OUT on one endpoint number
    def desc_cfg(self, desc, itf_num, ep_num, strs):
        desc.interface(itf_num, 2, 0x03, 0, 0, len(strs) if self.interface_str else 0)
        if self.interface_str:
            strs.append(self.interface_str)
        self.get_hid_descriptor(desc)
        self._int_ep = ep_num | _EP_IN_FLAG
        self._out_ep = ep_num
        desc.endpoint(self._int_ep, "interrupt", hp.REPORT_LEN, INTERVAL_MS)
        desc.endpoint(self._out_ep, "interrupt", hp.REPORT_LEN, INTERVAL_MS)
        self.idle_rate = 0
        self.protocol = 1

    def num_eps(self):
        return 1

    def on_open(self):
        super().on_open()
        self.submit_xfer(self._out_ep, self._rx_xfer, self._rx_done_cb)

    # ---- OUT: interrupt endpoint, and SET_REPORT on the control pipe
    def _push_rx(self, data):
        nxt = (self._rx_head + 1) % _SLOTS
        if nxt == self._rx_tail:
            return  # full: the command is lost, the host times out waiting for its ack
        self._rx[self._rx_head][:] = data
        self._rx_head = nxt

    def _rx_done(self, ep, result, xferred):
        if result == 0 and xferred == hp.REPORT_LEN:
            self._push_rx(self._rx_xfer)
        if self.is_open():
            self.submit_xfer(self._out_ep, self._rx_xfer, self._rx_done_cb)

    def on_set_report(self, report_data, report_id, report_type):
        if len(report_data) == hp.REPORT_LEN:
            self._push_rx(report_data)
        return True

    def recv(self, buf):
        if self._rx_tail == self._rx_head:
            return False
        buf[:] = self._rx[self._rx_tail]
        self._rx_tail = (self._rx_tail + 1) % _SLOTS
        return True

    # ---- IN
    def send(self, buf):
        nxt = (self._tx_head + 1) % _SLOTS
        if nxt == self._tx_tail or not self.is_open():
            self.dropped += 1
            return False
        self._tx[self._tx_head][:] = buf
        self._tx_head = nxt
        if not self.xfer_pending(self._int_ep):
            self._tx_next()
        return True

    def _tx_next(self):
        if self._tx_tail != self._tx_head:
            self.submit_xfer(self._int_ep, self._tx[self._tx_tail], self._tx_done_cb)

    def _tx_done(self, ep, result, xferred):
        self._tx_tail = (self._tx_tail + 1) % _SLOTS
        self._tx_next()
