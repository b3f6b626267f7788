"""The demo, run to run: what ``make demo`` shows, over several runs (docs/performance.md, "The demo, run to run").

Runs ``dyknow demo`` ``--runs`` times (default 3), each writing its report to a folder of its own,
and prints from each ``report.json``: when each adaptation came and why, in how many states the
requirement was false, the tracking error (where the camera saw the ball, and over the whole run,
predictions included) and what the warm standby cost beside what it saved; then the range of each
figure over the runs, with the load average at the end of each run.

    python benchmarks/demo.py [--runs 3] [--duration 30] [--json out/demo.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from harness import machine, write_json

#: The figures of a run printed as ranges, with their unit: (key of :func:`figures`, label, unit).
RANGED = (
    ("false_states", "requirement false in", "states"),
    ("states", "  of", "states"),
    ("seen_median_cm", "error where the ball was seen, median", "cm"),
    ("seen_p90_cm", "  90 % within", "cm"),
    ("all_median_cm", "error over the whole run, median", "cm"),
    ("all_p90_cm", "  90 % within", "cm"),
    ("standby_switch_ms", "a switch onto the warm standby, median", "ms"),
    ("cold_switch_ms", "a switch built cold, median", "ms"),
    ("standby_cost_pct", "what the standby cost", "% of a core"),
)


def run_demo(duration_s: float, out: Path) -> dict[str, Any]:
    """Run ``dyknow demo`` once into ``out``; its report's summary, with the load average at its end."""
    done = subprocess.run([sys.executable, "-m", "dyknow.cli", "demo", "--json", "--duration", str(duration_s), "--out", str(out)],
                          capture_output=True, text=True, timeout=duration_s + 300)  # fmt: skip
    if done.returncode != 0:
        raise SystemExit(f"dyknow demo failed ({done.returncode}): {done.stderr[-2000:]}")
    summary = dict(json.loads((out / "report.json").read_text())["summary"])
    summary["load"] = round(os.getloadavg()[0], 2)
    return summary


def figures(summary: dict[str, Any]) -> dict[str, float | None]:
    """The figures of one run that :data:`RANGED` prints."""
    standby = summary.get("standby") or {}
    cost = None
    if standby.get("cpu_with_pct") is not None and standby.get("cpu_without_pct") is not None:
        cost = round(standby["cpu_with_pct"] - standby["cpu_without_pct"], 1)
    return {
        "false_states": summary["requirement_false_states"],
        "states": summary["requirement_states"],
        "seen_median_cm": summary["measured_error_median_cm"],
        "seen_p90_cm": summary["measured_error_p90_cm"],
        "all_median_cm": summary["error_median_cm"],
        "all_p90_cm": summary["error_p90_cm"],
        "standby_switch_ms": standby.get("standby_switch_median_ms"),
        "cold_switch_ms": standby.get("cold_switch_median_ms"),
        "standby_cost_pct": cost,
    }


def adaptations(summary: dict[str, Any]) -> str:
    """When each adaptation came, to which camera, and why (its cause's first words)."""
    said = []
    for event in summary["adaptations"]:
        camera = next((unit for unit in event.get("to", []) if unit.endswith("-camera")), "?")
        said.append(f"{event['t_s']:.1f} s -> {camera} ({event['cause'].split(':')[0]})")
    return "; ".join(said) or "none"


def main() -> int:
    """Run the demo ``--runs`` times and print each run's figures and their ranges."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs of the demo (default 3)")
    parser.add_argument("--duration", type=float, default=30.0, help="seconds each run (default 30, the demo's own)")
    parser.add_argument("--json", type=Path, help="write every run's summary and figures here")
    args = parser.parse_args()
    if args.runs < 1 or args.duration < 5:
        parser.error(f"--runs {args.runs} --duration {args.duration}: expected at least 1 run of at least 5 s")
    runs = []
    with tempfile.TemporaryDirectory(prefix="dyknow-demo-runs-") as tmp:
        for k in range(args.runs):
            summary = run_demo(args.duration, Path(tmp) / f"run{k + 1}")
            runs.append({"summary": summary, "figures": figures(summary)})
            print(f"run {k + 1}: {adaptations(summary)}; load average {summary['load']}", flush=True)
    print()
    print(f"over {args.runs} runs of {args.duration:g} s:")
    for key, label, unit in RANGED:
        values = [run["figures"][key] for run in runs if run["figures"][key] is not None]
        shown = "n/a (no such switch in any run)" if not values else (
            f"{min(values):g} {unit}" if min(values) == max(values) else f"{min(values):g} to {max(values):g} {unit}")  # fmt: skip
        print(f"  {label:<42} {shown}")
    if args.json is not None:
        write_json(args.json, {"machine": machine(), "runs": runs, "duration_s": args.duration})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
