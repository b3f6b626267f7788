"""The pipeline robot without a managing system: its nodes brought up once, in a fixed mode.

``python -m dyknow.demo.pipeline.baseline [--mode SYSTEM=MODE ...]`` runs the robot of
:mod:`dyknow.demo.pipeline.robot` (the same options) and, as a robot with no managing system would,
brings its nodes up once through rclpy's own lifecycle and parameter clients, in the modes of
:data:`BASELINE_MODES` read from :data:`MODES_FILE` (each system's ``__DEFAULT__``, but the pipeline
followed once found), the motion controller last (its activation starts the mission's clock). Then
nothing changes whatever happens; it prints the same JSON measures as the robot.
"""

from __future__ import annotations

import json
import signal
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dyknow.demo.pipeline import MODES_FILE, robot
from dyknow.errors import DyKnowError, ServiceError

__all__ = ["BASELINE_MODES", "MODES_FILE", "ModeError", "NodeTarget", "fixed_mode", "main"]

#: The baseline's fixed mode of each system.
BASELINE_MODES: Mapping[str, str] = {
    "f_generate_search_path": "__DEFAULT__",
    "f_follow_pipeline": "fd_follow_pipeline",
    "f_maintain_motion": "__DEFAULT__",
}


class ModeError(DyKnowError):
    """A mode file or a mode asked of it is wrong (the message names the file, system and mode)."""


@dataclass(frozen=True, slots=True)
class NodeTarget:
    """A node of a mode: its name, whether it is to be active (else inactive) and its parameters."""

    node: str
    active: bool
    parameters: Mapping[str, Any]


def fixed_mode(modes: Mapping[str, str], path: str | Path = MODES_FILE) -> list[NodeTarget]:
    """The nodes of ``modes`` (system -> mode) in the system_modes file ``path``, in the order
    of the systems, then of their parts. Raises :class:`ModeError` for an unknown system, mode
    or part."""
    data = _yaml_load(Path(path).read_text(encoding="utf-8"))
    where = str(path)
    if not isinstance(data, dict):
        raise ModeError("not a mapping of systems and nodes", where=where, expected="a system_modes mode file")

    def body(name: str, kind: str) -> dict[str, Any]:
        entry = data.get(name)
        params = entry.get("ros__parameters") if isinstance(entry, dict) else None
        if not isinstance(params, dict) or params.get("type") != kind:
            known = sorted(k for k, v in data.items() if isinstance(v, dict) and v.get("ros__parameters", {}).get("type") == kind)
            raise ModeError(f"no {kind} {name!r}", where=where, expected=f"one of {', '.join(known)}")
        return params

    targets: list[NodeTarget] = []
    for system, mode in modes.items():
        spec = body(system, "system")
        parts = spec.get("modes", {}).get(mode)
        if not isinstance(parts, dict):
            raise ModeError(f"system {system!r} has no mode {mode!r}", where=where, expected=f"one of {', '.join(spec.get('modes', {}))}")
        for part, state in parts.items():
            target, _, part_mode = str(state).partition(".")
            if target not in ("active", "inactive"):
                raise ModeError(f"{system}.{mode}.{part}: state {state!r}", where=where, expected="'inactive', 'active' or 'active.MODE'")
            params: dict[str, Any] = {}
            if target == "active":
                node_modes = body(part, "node").get("modes", {})
                chosen = node_modes.get(part_mode or "__DEFAULT__")
                if not isinstance(chosen, dict):
                    raise ModeError(f"node {part!r} has no mode {part_mode!r}", where=where, expected=f"one of {', '.join(node_modes)}")
                params = dict(chosen.get("ros__parameters") or {})
            targets.append(NodeTarget(part, target == "active", params))
    return targets


def _yaml_load(text: str) -> Any:
    import yaml  # type: ignore[import-untyped]  # (no stubs) PyYAML comes with rclpy (its parameter files), which the baseline needs anyway

    return yaml.safe_load(text)


def _bring_up(targets: list[NodeTarget], context: Any, executor: Any, failed: list[str]) -> None:
    """Configure (and activate) each node, its parameters set first, through rclpy's clients;
    the motion controller last. A failure is put in ``failed`` and ends the run."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState
    from rcl_interfaces.srv import SetParameters
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    node = Node("baseline", context=context)
    executor.add_node(node)
    try:
        for target in sorted(targets, key=lambda t: t.node == "motion_controller"):

            def call(suffix: str, srv_type: Any, request: Any, target: NodeTarget = target) -> Any:
                client: Any = node.create_client(srv_type, f"/{target.node}/{suffix}")
                try:
                    if not client.wait_for_service(timeout_sec=15.0):
                        raise ServiceError(f"no /{target.node}/{suffix} within 15 s", where="baseline", expected="the robot's nodes up")
                    response = client.call(request, timeout_sec=15.0)
                    if response is None:
                        raise ServiceError(f"/{target.node}/{suffix} did not answer within 15 s", where="baseline")
                    return response
                finally:
                    node.destroy_client(client)

            if target.parameters:
                request = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in target.parameters.items()])
                results = call("set_parameters", SetParameters, request).results
                refused = [r.reason for r in results if not r.successful]
                if refused:
                    raise ServiceError(f"/{target.node} refused its parameters: {refused[0]}", where="baseline")
            transitions = [Transition.TRANSITION_CONFIGURE] + ([Transition.TRANSITION_ACTIVATE] if target.active else [])
            for transition in transitions:
                if not call("change_state", ChangeState, ChangeState.Request(transition=Transition(id=transition))).success:
                    raise ServiceError(f"/{target.node} refused transition {transition}", where="baseline")
            node.get_logger().info(f"/{target.node} {'active' if target.active else 'inactive'} {dict(target.parameters)}")
    except Exception as exc:  # the run ends, saying why (unless it was ending anyway: SIGTERM mid-way)
        if robot.running():
            failed.append(str(exc))
            robot.stop()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the no-adaptation baseline; prints the measures as one JSON line at the end."""
    parser = robot.argument_parser("python -m dyknow.demo.pipeline.baseline")
    parser.description = "The pipeline robot without a managing system: its nodes brought up once, in a fixed mode."
    parser.add_argument("--mode", action="append", default=[], metavar="SYSTEM=MODE", help="a system's fixed mode (default: BASELINE_MODES)")
    options, args = robot.parse_args(argv, parser)
    modes = dict(BASELINE_MODES)
    try:
        for item in args.mode:
            system, sep, mode = item.partition("=")
            if not sep or system not in modes:
                raise ModeError(f"--mode {item}", where="baseline", expected=f"SYSTEM=MODE with SYSTEM one of {', '.join(modes)}")
            modes[system] = mode
        targets = fixed_mode(modes)
        options.load_script()
    except DyKnowError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    failed: list[str] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: robot.stop())
    measures = robot.run(options, on_ready=lambda executor, context: _bring_up(targets, context, executor, failed))
    if failed:
        print(f"error: {failed[0]}", file=sys.stderr)
        return 1
    print(json.dumps(measures.to_dict()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
