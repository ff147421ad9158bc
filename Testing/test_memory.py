"""Tests of mdlshapemodel.memory: the memory a process frees goes back to the operating system."""

import ctypes
import subprocess
import sys
import textwrap

import pytest

def has_glibc() -> bool:
    try:
        ctypes.CDLL(None).gnu_get_libc_version
    except (OSError, AttributeError):
        return False
    return sys.platform.startswith("linux")


# what both scripts below start with: the process's resident MB
RESIDENT = textwrap.dedent("""
    import numpy as np
    from mdlshapemodel.memory import LOOP_RELEASE_SECONDS, release_freed_memory

    def resident_mb():
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmRSS"):
                    return int(line.split()[1]) / 1024
""")
# In a fresh process: many arrays of 256 KB from glibc's heap (a 16 MB array freed first lifts
# its threshold for mapping blocks on their own), every other one freed, so the free memory lies
# between blocks still in use, as after a build's stage. Prints the resident MB after the frees
# and after release_freed_memory.
FRAGMENTED = RESIDENT + textwrap.dedent("""
    big = np.ones(2_000_000)
    del big
    blocks = [np.ones(32_768) for _ in range(1600)]          # 400 MB of 256 KB each
    del blocks[::2]
    freed = resident_mb()
    released = release_freed_memory()
    print(freed, resident_mb(), released)
""")


@pytest.mark.skipif(not has_glibc(), reason="malloc_trim is glibc's")
def test_memory_freed_between_blocks_in_use_leaves_the_process():
    run = subprocess.run([sys.executable, "-c", FRAGMENTED], capture_output=True, text=True,
                         timeout=120, check=True)
    freed, after, released = run.stdout.split()
    assert released == "True"
    # 200 MB freed between the blocks kept: most of it leaves the resident set
    assert float(freed) - float(after) > 150.0, run.stdout



# As FRAGMENTED, twice: after a release, a second fragmenting; a release asked for inside a loop
# within LOOP_RELEASE_SECONDS of the first does nothing, one without the limit hands it back.
IN_A_LOOP = RESIDENT + textwrap.dedent("""
    def fragment():
        blocks = [np.ones(32_768) for _ in range(1600)]
        del blocks[::2]
        return blocks

    big = np.ones(2_000_000)
    del big
    kept = fragment()
    first = release_freed_memory(at_most_every=LOOP_RELEASE_SECONDS)
    kept += fragment()
    freed = resident_mb()
    skipped = release_freed_memory(at_most_every=LOOP_RELEASE_SECONDS)
    after_skip = resident_mb()
    released = release_freed_memory()
    print(first, skipped, freed, after_skip, resident_mb(), released)
""")


@pytest.mark.skipif(not has_glibc(), reason="malloc_trim is glibc's")
def test_a_release_in_a_loop_waits_for_its_interval_and_a_stage_end_does_not():
    run = subprocess.run([sys.executable, "-c", IN_A_LOOP], capture_output=True, text=True,
                         timeout=120, check=True)
    first, skipped, freed, after_skip, after, released = run.stdout.split()
    # the first release in a loop is made; the next, within the interval, is not
    assert (first, skipped, released) == ("True", "False", "True"), run.stdout
    assert float(freed) - float(after_skip) < 20.0, run.stdout
    assert float(after_skip) - float(after) > 150.0, run.stdout
