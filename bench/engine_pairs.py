"""This tree's bus engine against an earlier commit's, both polling at the same time.

A step of 5 % in the engine's CPU per transaction is far below what a virtual machine's
speed does between two runs a minute apart (the same code measured 225 and 540 µs per
transaction). So the two engines run at once, each in a process of its own polling the
reference plant of ``bench/bus_efficiency.py`` on a simulated line of its own, over the
same seconds: whatever the machine does, it does to both. Each process sleeps nearly all
the time (some 2 % of a core), so on two cores neither waits for the other. Two copies of
one commit measured this way differ by 0.95-1.05 in a pair, median 1.01.

The earlier commit's ``gateway`` package is taken from git (``git archive``) into a
temporary directory and put first on the child's path; the measuring code is this tree's
(so the earlier commit must have the engine's module paths ``bench/bus_efficiency.py``
imports), and each child simulates its line with its own package's ``gateway simulate``.
Per run it prints both figures and their ratio (new / old), per format the median and the
spread of the ratios.

Run from the repository root:
.venv/bin/python -m bench.engine_pairs --against REF [--runs 5] [--seconds 8] [--formats 19200-N-1]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import Any, Literal, cast

from gateway.wire.timing import LineFormat

Parity = Literal["N", "E", "O"]

ROOT = Path(__file__).resolve().parent.parent


def line_format(text: str) -> LineFormat:
    """``19200-N-1`` as a :class:`LineFormat`."""
    baudrate, parity, stopbits = text.split("-")
    return LineFormat(baudrate=int(baudrate), parity=cast("Parity", parity), stopbits=int(stopbits))


def child(text: str, seconds: float) -> None:
    """Measure the engine this process imports and print its figures as JSON."""
    import gateway  # noqa: PLC0415 - which one: said for the reader of the output
    from bench.bus_efficiency import measure, simulated_line  # noqa: PLC0415 - the child's gateway

    line = line_format(text)
    with simulated_line(line) as (port, referee):
        figures: dict[str, object] = dict(asyncio.run(measure(port, line, seconds)))
    figures |= {"timing_violations": referee["timing_violations"], "gateway": gateway.__file__}
    print(json.dumps(figures), flush=True)


def earlier_gateway(ref: str, into: Path) -> Path:
    """Commit ``ref``'s ``gateway`` package under ``into``; the directory to put on the path."""
    archive = subprocess.run(  # noqa: S603 - git, with a ref the user gave
        ["git", "-C", str(ROOT), "archive", "--format=tar", ref, "gateway"],  # noqa: S607
        capture_output=True,
        check=True,
    ).stdout
    tar_path = into / "gateway.tar"
    tar_path.write_bytes(archive)
    with tarfile.open(tar_path) as tar:
        tar.extractall(into, filter="data")
    return into


def start(text: str, seconds: float, gateway_from: Path) -> subprocess.Popen[str]:
    """A child measuring the ``gateway`` package found in ``gateway_from``.

    That directory is the child's working directory, first on its module path (``-m``
    puts it before ``PYTHONPATH``); this tree, for ``bench``, follows.
    """
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(  # noqa: S603 - our own bench
        [sys.executable, "-m", "bench.engine_pairs", "--child", text, "--seconds", repr(seconds)],
        cwd=gateway_from,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )


def figures_of(process: subprocess.Popen[str], seconds: float) -> dict[str, Any]:
    out, _ = process.communicate(timeout=seconds + 60)
    if process.returncode != 0 or not out.strip():
        raise SystemExit(f"a measuring process failed (exit {process.returncode})")
    figures: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--against", help="the earlier commit (any git ref)")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--formats", default="19200-N-1", help="BAUD-PARITY-STOPBITS list")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child, args.seconds)
        return
    if not args.against:
        parser.error("--against REF is needed")
    with tempfile.TemporaryDirectory() as tmp:
        old_tree = earlier_gateway(args.against, Path(tmp))
        print(
            f"{'line':<12} {'run':>3} {'new µs/tx':>9} {'old µs/tx':>9} {'new/old':>7} "
            f"{'tx/s new':>8} {'tx/s old':>8} {'errors':>6} {'viol':>4}"
        )
        for text in args.formats.split(","):
            ratios = []
            for run in range(args.runs):
                new = start(text, args.seconds, ROOT)
                old = start(text, args.seconds, old_tree)
                fn, fo = figures_of(new, args.seconds), figures_of(old, args.seconds)
                ratio = fn["cpu_us_per_transaction"] / fo["cpu_us_per_transaction"]
                ratios.append(ratio)
                if run == 0:
                    print(f"new engine: {fn['gateway']}\nold engine: {fo['gateway']}")
                print(
                    f"{text:<12} {run + 1:>3} {fn['cpu_us_per_transaction']:>9.0f} "
                    f"{fo['cpu_us_per_transaction']:>9.0f} {ratio:>7.3f} "
                    f"{fn['transactions_per_s']:>8.1f} {fo['transactions_per_s']:>8.1f} "
                    f"{fn['errors'] + fo['errors']:>6.0f} "
                    f"{fn['timing_violations'] + fo['timing_violations']:>4.0f}",
                    flush=True,
                )
            print(
                f"{text}: new/old median {statistics.median(ratios):.3f} "
                f"({min(ratios):.3f}-{max(ratios):.3f}), {args.runs} runs against {args.against}"
            )


if __name__ == "__main__":
    main()
