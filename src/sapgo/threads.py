"""How many threads the kernels run on: every core on an idle machine, one while other
processes want the cores.

numba's parallel kernels run on GNU OpenMP, whose threads spin for a while (about a
millisecond) between two parallel regions before they sleep; the band factorisation alone
meets at a barrier once a panel, thousands of times an iteration. On an idle machine the
spinning saves a wake-up a region. With more runnable threads than cores, a spinning thread
holds the core that the thread with the work needs, and every region waits for the
scheduler: on 2 cores (benchmarks/contention.py, 10 000 photos, every thread throughout) an
adjustment took 3.7 s beside one busy process and 35 s beside another adjustment, against
1.7 s alone. Making the
threads sleep at once (``OMP_WAIT_POLICY=PASSIVE``) cures the contended case but costs the
idle one 1.7 times (a sleeping virtual CPU is slow to wake).

So sapgo looks before each parallel step (at most every :data:`CHECK_SECONDS`): when
:data:`CONFIRM` looks in a row find a thread of another process runnable (``/proc/stat``'s ``procs_running`` less this
process's own running threads), the kernels launched from this thread run on one thread
(``numba.set_num_threads(1)``: no team, no barrier, nothing spins), and the precision
pass's BLAS calls on one thread too, until the machine has been free of other runnable
threads for :data:`HOLD_SECONDS`; then on all of them again. (The partition tree's fronts
keep their BLAS threads.)
Results do not depend on it: every kernel splits its work by its own count of parts, not by
the threads that run them.

``SAPGO_THREADS``: "auto" (the default, the above), or a whole number of threads used
throughout (no looking; more than numba's threads counts as numba's threads); anything else
is refused with :class:`~sapgo.errors.ParameterError`. Without ``/proc`` (not Linux) the kernels use numba's threads throughout.
"""

from __future__ import annotations

import os
import threading
import time

import numba

from .errors import ParameterError

#: Seconds between two looks at the machine (a look costs about 0.1 ms: 90 microseconds
#: measured: /proc/stat and each of this process's threads' stat; at most half a per cent of
#: a thread's time).
CHECK_SECONDS = 0.02
#: Seconds without other runnable threads before the kernels use every thread again.
HOLD_SECONDS = 0.5
#: Looks in a row that must find other runnable threads: single looks found one now and
#: then on an idle machine (3-6 % of them: system threads passing, this process's own
#: threads between their states), enough to put an idle run on one thread a quarter of
#: its time.
CONFIRM = 2

_setting = os.environ.get("SAPGO_THREADS", "auto").strip().lower() or "auto"
_local = threading.local()
#: Looks at the machine and how many found other processes running (for the report).
STATS = {"checks": 0, "busy": 0}


def _fixed():
    """``SAPGO_THREADS`` as a number of threads, or None for "auto"."""
    if _setting == "auto":
        return None
    try:
        n = int(_setting)
    except ValueError:
        n = 0
    if n < 1:
        raise ParameterError(f"SAPGO_THREADS={_setting!r}: expected 'auto' or a whole "
                             f"number of threads of at least 1")
    return min(n, numba.config.NUMBA_NUM_THREADS)


def parts():
    """How many parts a parallel kernel splits its work into: numba's thread count (or
    ``SAPGO_THREADS`` when it is a number), whatever number of threads then runs them."""
    fixed = _fixed()
    return numba.config.NUMBA_NUM_THREADS if fixed is None else fixed


def _procs_running():
    with open("/proc/stat", "rb") as f:
        for line in f:
            if line.startswith(b"procs_running"):
                return int(line.split()[1])
    raise OSError("no procs_running in /proc/stat")


def _own_running():
    n = 0
    for tid in os.listdir("/proc/self/task"):   # (glob's pattern matching: 2x the look)
        try:
            with open(f"/proc/self/task/{tid}/stat", "rb") as f:
                s = f.read()
        except OSError:   # (a thread that ended meanwhile)
            continue
        if s[s.rindex(b")") + 2:s.rindex(b")") + 3] == b"R":
            n += 1
    return n


def others_running():
    """Runnable threads of other processes now (None without ``/proc``)."""
    try:
        return max(0, _procs_running() - max(1, _own_running()))
    except (OSError, ValueError, IndexError):
        return None


def adapt():
    """Before a parallel step: set numba's threads for kernels launched from this thread
    (one while other processes are running, else :func:`parts`). Returns the count."""
    full = parts()
    if _fixed() is not None or full == 1:
        if numba.get_num_threads() != full:
            numba.set_num_threads(full)
        return full
    now = time.monotonic()
    st = _local.__dict__
    if now - st.get("checked", -1.0) >= CHECK_SECONDS:
        st["checked"] = now
        others = others_running()
        if others is None:
            st["busy_until"] = -1.0
        else:
            STATS["checks"] += 1
            st["streak"] = st.get("streak", 0) + 1 if others > 0 else 0
            if st["streak"] >= CONFIRM:   # (a passing thread is no competitor)
                STATS["busy"] += 1
                st["busy_until"] = now + HOLD_SECONDS
    n = 1 if now < st.get("busy_until", -1.0) else full
    if numba.get_num_threads() != n:
        numba.set_num_threads(n)
    return n


def busy_share():
    """The share of looks that found other processes running, or None (no looks)."""
    return STATS["busy"] / STATS["checks"] if STATS["checks"] else None
