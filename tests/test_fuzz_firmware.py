"""A seeded command fuzz of the whole firmware in the MicroPython VM (tests/mp_fuzz.py):
>= 10 000 OUT reports per run, each handled inside a real heap-locked frame. A refused
report changes nothing, every pulse stays inside the hard and soft limits and on an
armed channel, every accepted setting obeys the device's rules. The seed is printed
(pytest -s, or the failure message); FUZZ_SEED=N replays one. CI uses fixed seeds so a
landing never depends on luck; local runs draw new ones. bench/fuzz.py runs millions."""

import os
import random
import subprocess

import pytest

from conftest import FIRMWARE, ROOT, SHARED

N_REPORTS = 12_000


def _seed(k):
    if os.environ.get("FUZZ_SEED"):
        return int(os.environ["FUZZ_SEED"]) + k
    if os.environ.get("CI"):
        return 1000 + k
    return random.SystemRandom().randrange(1, 2**31)


@pytest.mark.parametrize("k", [0])
def test_firmware_command_fuzz(micropython, k):
    seed = _seed(k)
    print(f"firmware fuzz seed {seed} (replay: FUZZ_SEED={seed - k})")
    env = dict(os.environ, MICROPYPATH=os.pathsep.join([str(SHARED), str(FIRMWARE)]))
    p = subprocess.run([micropython, str(ROOT / "tests" / "mp_fuzz.py"), str(seed), str(N_REPORTS)],
                       capture_output=True, text=True, env=env, timeout=600)
    last = (p.stdout.strip().splitlines() or [""])[-1]
    assert p.returncode == 0 and last.startswith("OK"), f"seed {seed}: {last}\n{p.stderr[-2000:]}"
    assert f"reports={N_REPORTS} " in last
    pulses = int(last.split("pulses=")[1].split()[0])
    accepted = int(last.split("results=")[1].split(",")[0].split(":")[1])
    assert pulses > N_REPORTS // 4 and accepted > N_REPORTS // 5, last  # the fuzz reaches armed, pulsing states
