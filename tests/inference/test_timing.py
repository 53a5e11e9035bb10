"""The stage timer: wall, process CPU and the calling thread's own CPU time per stage, from several threads, and
each block's own duration."""

from __future__ import annotations

import threading
import time

from dfvo.inference.timing import StageTimer


def _burn(seconds: float) -> None:
    end = time.thread_time() + seconds
    x = 0
    while time.thread_time() < end:
        x += 1


def test_a_stage_counts_its_own_thread_cpu_and_the_process_cpu_of_every_thread() -> None:
    """A worker burns 0.3 s of CPU in stage "work" while the main thread sleeps 0.4 s in stage "wait": "wait" has
    ~0 CPU of its own thread but the worker's CPU in the process time; "work" has ~0.3 s of its own."""
    timer = StageTimer()
    started = threading.Event()

    def worker() -> None:
        started.set()
        with timer("work"):
            _burn(0.3)

    t = threading.Thread(target=worker)
    with timer("wait"):
        t.start()
        started.wait()
        time.sleep(0.4)
        t.join()
    own = timer.thread_cpu_ms_per_frame(1)
    proc = timer.cpu_ms_per_frame(1)
    wall = timer.ms_per_frame(1)
    assert own["wait"] < 50 and proc["wait"] >= 250 and wall["wait"] >= 390
    assert 280 <= own["work"] <= 600 and own["work"] <= proc["work"] + 5
    with timer("lap") as lap:  # each block hands back its own duration, whatever other threads time meanwhile
        time.sleep(0.05)
    assert lap.seconds >= 0.05 and timer.ms_per_frame(1)["lap"] == 1000.0 * lap.seconds
    timer.add("load", 0.01, 0.02, 0.005)  # a stage timed by its caller (the loader thread)
    assert timer.thread_cpu_ms_per_frame(2)["load"] == 2.5
