# For the MicroPython command drivers (mp_fw_driver.py, mp_fuzz.py): wrap a
# Stimulator's command handler so each command's settings digest is taken just
# before and after it. The handler runs inside the frame's heap lock; the digests
# are taken with the lock lifted for a moment, the handler itself runs locked.
import micropython


def watch(s, digest):
    """Returns seen = [digest before, digest after, commands handled]."""
    seen = ["", "", 0]
    handle = s.handle

    def watched(r, now):
        micropython.heap_unlock()
        seen[0] = digest()
        micropython.heap_lock()
        res = handle(r, now)
        micropython.heap_unlock()
        seen[1] = digest()
        seen[2] += 1
        micropython.heap_lock()
        return res

    s.handle = watched
    return seen
