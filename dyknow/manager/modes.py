"""What a manager says of system modes: each system in a mode, since when, and why that mode.

A system is in a mode while the mode's unit runs (:class:`~dyknow.ros2.modes.ModeUnit`, a spec's
``<system>``). :func:`mode_infos` lists them for the model (``dyknow model``, the browser tool),
the metrics (``dyknow_system_mode``) and ``/diagnostics``: ``{"system", "mode", "transformation",
"unit", "request", "since_ns", "why", "constraints"}``. ``why`` is the cause of the adaptation
that chose the mode (``measurement visibility = 0.6 ...``, ``unit 'search.high' failed ...``), or,
for the mode chosen when the system was requested, that it was the preferred mode whose
constraints held; ``constraints`` are the mode's, each with the measure's latest value.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from dyknow.adaptation import AdaptationEvent
from dyknow.model import RequestInfo, UnitInfo
from dyknow.spec.model import MODE_UNIT_SOURCE

__all__ = ["mode_infos"]


def mode_infos(
    units: Iterable[UnitInfo], requests: Iterable[RequestInfo], history: Sequence[AdaptationEvent], measurements: Mapping[str, float | str]
) -> list[dict[str, Any]]:
    """The systems in a mode now (see the module's documentation), by system."""
    serving = {unit: request for request in requests for unit in request.units}
    out = []
    for info in units:
        spec = info.spec
        if spec is None or spec.source != MODE_UNIT_SOURCE or info.state not in ("running", "stalled"):
            continue
        params = {p.name: p.value for p in spec.params}
        request = serving.get(info.name)
        chosen = next((e for e in reversed(history) if request is not None and e.key == request.key and e.kind == "adapted" and info.label in e.new), None)
        constraints = [
            {"measure": c.measure, "op": c.op, "value": c.value, "margin": c.margin, "measured": measurements.get(c.measure)} for c in spec.constraints
        ]
        if chosen is not None:
            why = chosen.cause
        elif request is not None:
            held = ", ".join(f"{c['measure']} = {c['measured']!r} {c['op']} {c['value']!r}" for c in constraints if c["measured"] is not None)
            why = f"requested {request.tag}: the preferred mode whose constraints hold" + (f" ({held})" if held else "")
        else:
            why = "spawned by hand"
        out.append(
            {
                "system": str(params.get("system", "")),
                "mode": str(params.get("mode", "")),
                "transformation": info.label,
                "unit": info.name,
                "request": request.key if request is not None else None,
                "since_ns": info.started_ns,
                "why": why,
                "constraints": constraints,
            }
        )
    return sorted(out, key=lambda m: (m["system"], m["unit"]))
