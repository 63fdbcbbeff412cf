"""What a ``wbc-jax`` command's main thread spends its wall time on, in order: a sampled timeline.

    python examples/wall_timeline.py [--every 0.01] [--bin 0.2] [--samples FILE] campaign --spec SPEC --out DIR

The command runs in this process as the console script runs it (``wbc_jax.cli.run``) while a thread reads the main
thread's stack every ``--every`` seconds (``sys._current_frames``). Each sample is named by the innermost frame of
the ``wbc_jax`` package (module path and function), prefixed ``import`` while Python imports a module below it. The
samples are grouped in bins of ``--bin`` seconds, each bin named by its most frequent name, and consecutive bins of
one name merged: the printed stretches (start, end, name) are the phases of the command's wall time, waits included
(a device call, a thread joined), which a profiler of CPU time (``cProfile``) attributes to whatever holds the
interpreter meanwhile. Times are from the start of this script. ``--samples FILE`` also writes every sample (time,
name, innermost frame).
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from collections import Counter


def frame_name(frame) -> tuple[str, str]:
    """(the sample's name, its innermost frame as ``file:function``) of a stack whose innermost frame is ``frame``."""
    inner = f"{os.path.basename(frame.f_code.co_filename)}:{frame.f_code.co_name}"
    importing = False
    while frame is not None:
        path = frame.f_code.co_filename
        if "/wbc_jax/" in path:
            name = f"{path.split('/wbc_jax/')[-1]}:{frame.f_code.co_name}"
            return ("import in " + name if importing else name), inner
        importing = importing or path.startswith("<frozen importlib")
        frame = frame.f_back
    return ("import" if importing else inner), inner


def phases(samples: list[tuple[float, str]], bin_s: float) -> list[tuple[float, float, str]]:
    """(start, end, name) stretches of ``samples`` ((time [s], name), in time order): bins of ``bin_s`` seconds named
    by their most frequent name, consecutive bins of one name merged."""
    bins: dict[int, Counter] = {}
    for t, name in samples:
        bins.setdefault(int(t / bin_s), Counter())[name] += 1
    runs: list[list] = []  # [first bin, last bin, name]
    for b in sorted(bins):
        name = bins[b].most_common(1)[0][0]
        if runs and runs[-1][2] == name and runs[-1][1] == b - 1:
            runs[-1][1] = b
        else:
            runs.append([b, b, name])
    return [(first * bin_s, (last + 1) * bin_s, name) for first, last, name in runs]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--every", type=float, default=0.01, help="seconds between samples (default 0.01)")
    parser.add_argument("--bin", type=float, default=0.2, help="seconds per bin of the timeline (default 0.2)")
    parser.add_argument("--samples", help="also write every sample to this file (tab-separated)")
    args, command = parser.parse_known_args()
    if not command or args.every <= 0 or args.bin <= 0:
        parser.error("give a wbc-jax command after the options, and --every, --bin > 0")
    t0, main_id, samples, stop = time.perf_counter(), threading.get_ident(), [], threading.Event()

    def sample():
        while not stop.is_set():
            frame = sys._current_frames().get(main_id)
            if frame is not None:
                samples.append((time.perf_counter() - t0, *frame_name(frame)))
            time.sleep(args.every)

    def report():  # an exit handler: once the command has returned and its threads have ended
        stop.set()
        print(f"\nwbc-jax {' '.join(command)}: {time.perf_counter() - t0:.2f} s; the main thread's phases (bins of "
              f"{args.bin} s):")
        for start, end, name in phases([(t, name) for t, name, _ in samples], args.bin):
            print(f"{start:8.1f} {end:8.1f} s {end - start:7.1f} s  {name}")
        if args.samples:
            with open(args.samples, "w") as f:
                f.writelines(f"{t:.3f}\t{name}\t{inner}\n" for t, name, inner in samples)

    threading.Thread(target=sample, name="wall-timeline", daemon=True).start()
    import atexit

    from wbc_jax.cli import run

    atexit.register(report)
    sys.argv = ["wbc-jax", *command]
    run()  # the console script: the command, its threads joined, the exit handlers, then the process ends


if __name__ == "__main__":
    main()
