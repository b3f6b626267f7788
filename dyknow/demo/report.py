"""The demo's report: a JSON summary, a plot of the track with the adaptations marked, a frame."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dyknow.adaptation import AdaptationEvent

__all__ = ["write_report"]


def write_report(
    out_dir: Path,
    *,
    start_ns: int,
    request: str,
    key: str,
    track: list[tuple[int, int, dict[str, Any]]],
    scene: Any,
    battery: list[tuple[float, float]],
    events: list[AdaptationEvent],
    frame: Any,
    statistics: dict[str, Any],
    say: Callable[[str], None],
    requirement: str | None = None,
    verdicts: list[tuple[int, bool]] | None = None,
    standby: dict[str, Any] | None = None,
    ros2: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write ``report.json``, ``track.png`` and ``frame.png`` into ``out_dir``; returns the report.

    ``requirement`` and its ``verdicts`` (state time ns, verdict): the request's requirement,
    summarised, listed and plotted. ``standby``: whether the request had a warm standby
    (``"warm"``) and the process's CPU with and without one running (:class:`_CpuShare`'s
    shares); the summary sets what it cost beside what its switches saved. ``ros2``: what
    crossed the ROS 2 boundary (the ROS 2 variant), in the summary."""
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = start_ns  # times in the report are seconds since the demo started (when the battery trace starts)
    rows = []
    for arrival_ns, origin_ns, p in track:
        row: dict[str, Any] = {
            "t_s": round((arrival_ns - t0) / 1e9, 3),
            "x": p.get("x"),
            "y": p.get("y"),
            "vx": p.get("vx"),
            "vy": p.get("vy"),
            "predicted": p.get("predicted"),
            "age_ms": round((arrival_ns - origin_ns) / 1e6, 2),
        }
        if scene is not None and isinstance(p.get("x"), (int, float)):
            truth = scene.ball_at(origin_ns)
            row.update(
                truth_x=round(truth.x, 4),
                truth_y=round(truth.y, 4),
                error_cm=round(math.hypot(p["x"] - truth.x, p["y"] - truth.y) * 100, 2),
            )
        rows.append(row)
    finals = {e.id: e for e in events}  # the recovered version replaces the adapted one
    adaptations = [
        {
            "t_s": round((e.fault_ns - t0) / 1e9, 3),
            "kind": e.kind,
            "cause": e.cause,
            "from": list(e.old),
            "to": list(e.new),
            "adaptation_ms": e.adaptation_ms,
            "recovery_ms": e.recovery_ms,
            "standby": e.standby,
            "detail": e.detail,
        }
        for e in sorted(finals.values(), key=lambda e: e.fault_ns)
    ]
    gaps = [(b[0] - a[0]) / 1e6 for a, b in zip(track, track[1:], strict=False)]
    errors = sorted(r["error_cm"] for r in rows if "error_cm" in r)
    measured = sorted(r["error_cm"] for r in rows if "error_cm" in r and not r["predicted"])
    standby_summary = _standby_summary(standby or {}, adaptations)
    summary = {
        "request": request,
        "key": key,
        "track_messages": len(rows),
        "duration_s": rows[-1]["t_s"] if rows else 0.0,
        "longest_gap_ms": round(max(gaps), 1) if gaps else None,
        "error_median_cm": errors[len(errors) // 2] if errors else None,
        "error_p90_cm": errors[int(len(errors) * 0.9)] if errors else None,
        # the same over the messages where the camera saw the ball (the rest are predictions)
        "measured_error_median_cm": measured[len(measured) // 2] if measured else None,
        "measured_error_p90_cm": measured[int(len(measured) * 0.9)] if measured else None,
        "predicted_messages": sum(1 for r in rows if r["predicted"]),
        "adaptations": adaptations,
        "requirement": requirement,
        "requirement_states": len(verdicts or []),
        "requirement_false_states": sum(1 for _, v in verdicts or [] if not v),
        "standby": standby_summary,
    }
    if ros2 is not None:
        summary["ros2"] = ros2
    judged = [{"t_s": round((t - t0) / 1e9, 3), "verdict": v} for t, v in verdicts or []]
    report = {
        "summary": summary,
        "track": rows,
        "battery": [{"t_s": round(t, 3), "level": round(b, 3)} for t, b in battery],
        "verdicts": judged,
        "statistics": statistics,
    }
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    written = ["report.json"]
    if _plot(out_dir / "track.png", rows, battery, adaptations, scene is not None, judged):
        written.append("track.png")
    if frame is not None:
        import cv2

        if cv2.imwrite(str(out_dir / "frame.png"), frame):
            written.append("frame.png")
    say("")
    say(
        f"{len(rows)} track messages on {key}, {summary['predicted_messages']} of them predicted while the camera did not see "
        f"the ball; longest gap {summary['longest_gap_ms']} ms (no track while the ball was out of view)"
    )
    if errors:
        say(
            f"tracking error against the ground truth: median {summary['error_median_cm']} cm, 90% under {summary['error_p90_cm']} cm; "
            f"where the ball was seen: median {summary['measured_error_median_cm']} cm, 90% under {summary['measured_error_p90_cm']} cm"
        )
    if requirement:
        say(f"requirement {requirement}: false in {summary['requirement_false_states']} of {summary['requirement_states']} states")
    for a in adaptations:
        if a["kind"] != "degraded":
            onto = " onto the warm standby" if a["standby"] else ""
            say(f"adaptation at {a['t_s']:.1f} s ({a['cause']}): adapted{onto} in {a['adaptation_ms']} ms, recovered in {a['recovery_ms']} ms")
    say(_standby_line(standby_summary))
    say(f"report written to {out_dir.resolve()} ({', '.join(written)})")
    return report


def _plot(
    path: Path,
    rows: list[dict[str, Any]],
    battery: list[tuple[float, float]],
    adaptations: list[dict[str, Any]],
    truth: bool,
    verdicts: list[dict[str, Any]] | None = None,
) -> bool:
    try:
        import matplotlib
    except ImportError:
        return False
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_x, ax_y, ax_b) = plt.subplots(3, 1, figsize=(11.5, 7), sharex=True, gridspec_kw={"height_ratios": [3, 3, 1.5]})
    t = [r["t_s"] for r in rows]
    for ax, coord in ((ax_x, "x"), (ax_y, "y")):
        ax.plot(t, [r[coord] for r in rows], ".", markersize=2, label=f"tracked {coord}")
        if truth:
            ax.plot(t, [r.get(f"truth_{coord}") for r in rows], "-", linewidth=0.8, alpha=0.7, label="ground truth")
        ax.set_ylabel(f"{coord} (m)")
        ax.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8, frameon=False)  # beside the plot: it hides nothing
    ax_b.plot([b[0] for b in battery], [b[1] for b in battery], color="tab:green")
    ax_b.axhline(0.25, color="grey", linestyle=":", linewidth=0.8)
    ax_b.set_ylabel("battery")
    if verdicts:  # the requirement's verdicts along the bottom: green holds, red violated
        for value, colour in ((True, "tab:green"), (False, "tab:red")):
            times = [v["t_s"] for v in verdicts if v["verdict"] is value]
            ax_b.plot(times, [0.02] * len(times), "|", color=colour, markersize=6, label=f"requirement {'holds' if value else 'false'}")
        ax_b.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7, frameon=False)
    ax_b.set_xlabel("time (s)")
    switches = [a for a in adaptations if a["kind"] != "degraded"]
    for i, a in enumerate(switches):
        camera = next((x for x in a["to"] if "camera" in x), "?")
        for ax in (ax_x, ax_y, ax_b):
            ax.axvline(a["t_s"], color="tab:red", linewidth=1)
        ax_x.annotate(  # staggered, so that switches close in time do not overwrite each other
            f"{i + 1}: -> {camera}",
            (a["t_s"], 1),
            xycoords=("data", "axes fraction"),
            xytext=(3, -11 - 10 * (i % 3)),
            textcoords="offset points",
            color="tab:red",
            fontsize=7,
            bbox={"boxstyle": "square,pad=0.1", "facecolor": "white", "edgecolor": "none", "alpha": 0.8},
        )
    fig.suptitle("dyknow demo: the tracked ball, with the adaptations (red)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def _median(values: list[float]) -> float | None:
    ordered = sorted(values)
    return ordered[len(ordered) // 2] if ordered else None


def _standby_summary(standby: dict[str, Any], adaptations: list[dict[str, Any]]) -> dict[str, Any]:
    """What the warm standby cost and saved: the CPU shares with and without one running, and the
    switches onto it against the switches that built their configuration cold."""
    switches = [a for a in adaptations if a["kind"] != "degraded" and a["adaptation_ms"] is not None]
    warm = [a["adaptation_ms"] for a in switches if a["standby"]]
    cold = [a["adaptation_ms"] for a in switches if not a["standby"]]
    return {
        **standby,
        "switches_onto_standby": len(warm),
        "standby_switch_median_ms": _median(warm),
        "cold_switches": len(cold),
        "cold_switch_median_ms": _median(cold),
    }


def _standby_line(s: dict[str, Any]) -> str:
    if not s.get("warm"):
        cold = f"{s['cold_switch_median_ms']} ms median over {s['cold_switches']}" if s["cold_switches"] else "none"
        return f"no warm standby (--no-standby): switches built their configuration cold: {cold}"
    saved = "no switch onto it"
    if s["switches_onto_standby"]:
        saved = f"{s['switches_onto_standby']} switches onto it took {s['standby_switch_median_ms']} ms median"
        saved += f", against {s['cold_switch_median_ms']} ms for the {s['cold_switches']} built cold" if s["cold_switches"] else " (none built cold)"
    with_, without = s.get("cpu_with_pct"), s.get("cpu_without_pct")
    cost = "its cost was not measured (no time both with and without one)"
    if with_ is not None and without is not None:
        cost = (
            f"it cost {with_ - without:+.1f} % of a core (the process used {with_} % of one in the {s['seconds_with']} s a "
            f"standby ran, {without} % in the {s['seconds_without']} s none could: the battery was low)"
        )
    return f"warm standby: {saved}; {cost}"
