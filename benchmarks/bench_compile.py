"""Which numba kernels a ``vhm-viz`` command compiles on a first run, and what each costs.

Runs the command in this process with an empty compiled-code cache (a scratch
``NUMBA_CACHE_DIR``) and listens to numba's ``numba:compile`` events. Each kernel's row
holds its *exclusive* CPU seconds: its own compile, plus that of numba's internal
overloads it pulls in (``np.empty``, string formatting, linear algebra wrappers), but not
the vhm_viz kernels it calls, which have rows of their own. A kernel compiled for several
argument types lists each signature: such duplicates are compile time a caller can save by
passing one dtype and layout.

    python benchmarks/bench_compile.py demo -o /tmp/demo -q
    python benchmarks/bench_compile.py --top 20 deform in.vti --scene s.json -o out.vts -q

Prints the process's CPU and wall time, the compile total, then the kernels by seconds.
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import tempfile
import time


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--top", type=int, default=40, help="kernels to list (default 40)")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="the vhm-viz command and its args")
    args = ap.parse_args(argv)
    if not args.command:
        ap.error("give a vhm-viz command, e.g. demo -o /tmp/demo -q")
    with tempfile.TemporaryDirectory(prefix="bench_compile_") as cache:
        os.environ["NUMBA_CACHE_DIR"] = cache  # before numba is imported
        from numba.core import event

        records = []  # (kernel, signature, exclusive seconds)
        stack = []  # [start CPU, children's CPU, vhm_viz owner or None, name]

        def name_of(data) -> str:
            f = data["dispatcher"].py_func
            return f"{f.__module__}.{f.__qualname__}"

        class Listener(event.Listener):
            def on_start(self, ev):
                name = name_of(ev.data)
                owner = name if name.startswith("vhm_viz") else None
                if owner is None and stack:
                    owner = stack[-1][2]
                stack.append([time.process_time(), 0.0, owner, name, str(ev.data["args"])])

            def on_end(self, ev):
                t0, children, owner, name, sig = stack.pop()
                spent = time.process_time() - t0
                records.append((owner or name, sig if owner == name else None, spent - children))
                if stack:
                    stack[-1][1] += spent

        event.register("numba:compile", Listener())
        cpu0, wall0 = time.process_time(), time.perf_counter()
        from vhm_viz.cli import main as cli_main

        try:
            status = cli_main(args.command)
        except SystemExit as exc:
            status = exc.code
        cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    total = sum(r[2] for r in records)
    by_kernel: dict = collections.defaultdict(lambda: [0.0, []])
    for kernel, sig, seconds in records:
        by_kernel[kernel][0] += seconds
        if sig is not None:
            by_kernel[kernel][1].append(sig)
    print(f"exit {status}; CPU {cpu:.1f} s, wall {wall:.1f} s, load {os.getloadavg()[0]:.1f}")
    print(f"compiling: {total:.1f} s CPU in {len(records)} compiles, {len(by_kernel)} kernels\n")
    ranked = sorted(by_kernel.items(), key=lambda kv: -kv[1][0])
    for kernel, (seconds, sigs) in ranked[: args.top]:
        more = f"  ({len(sigs)} signatures)" if len(sigs) > 1 else ""
        print(f"{seconds:7.2f} s  {kernel}{more}")
        if len(sigs) > 1:
            for sig in sigs:
                print(f"             {sig[:160]}")
    return 0 if status in (0, None) else 1


if __name__ == "__main__":
    sys.exit(main())
