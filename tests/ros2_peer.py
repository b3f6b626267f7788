"""An rmw_zenoh counterparty dyknow did not write: zenoh-ros2-sdk (PyPI), run as a child process.

    python tests/ros2_peer.py PORT talk TOPIC TYPE      publish every 20 ms until stdin closes (the i-th
                                                        TwistStamped: stamp sec=i, nanosec=5, twist.linear.x = i % 2)
    python tests/ros2_peer.py PORT listen TOPIC TYPE [transient_local]
                                                        print each message received, one JSON line (a
                                                        diagnostic_msgs/msg/DiagnosticArray as {"statuses": [...]})
    python tests/ros2_peer.py PORT info TOPIC           print `ros2 topic info -v` once a publisher shows
    python tests/ros2_peer.py PORT serve SERVICE TYPE   serve a lifecycle service (GetState: active;
                                                        ChangeState: success for transition 3), print each request
    python tests/ros2_peer.py PORT call SERVICE TYPE JSON
                                                        call once (JSON: the request's fields), print the response
    python tests/ros2_peer.py PORT lifecycle NAME TOPIC a lifecycle node as rclpy.lifecycle's behaves, built on the
                                                        SDK's service servers and publisher (the SDK has no lifecycle
                                                        node): /NAME/get_state, /NAME/change_state and
                                                        /NAME/set_parameters (a double "exposure"); publishes
                                                        std_msgs/String on TOPIC every 20 ms while active; prints each
                                                        transition and publishes it on /NAME/transition_event; a line "fail" on stdin: an error (ErrorProcessing,
                                                        then unconfigured), "quiet-fail": unconfigured with no
                                                        transition_event, "refuse-activate": activation fails
                                                        (it stays inactive; printed once taken), "stall": stop publishing

It connects to a Zenoh peer at tcp/127.0.0.1:PORT (the manager under test), as rmw_zenoh's
sessions connect to their router. Types and hashes come from ROS 2's own files (the ros-std-msgs,
ros-sensor-msgs and ros-diagnostic-msgs wheels' share/<pkg>/msg/*.msg and *.json), so the SDK never fetches a
definition from the network. Prints {"ready": true} once its entities are declared.
"""

from __future__ import annotations

import json
import re
import sys
import threading
import time
from pathlib import Path

SHARE = Path(sys.prefix) / "share"
DEPENDENCIES = {
    "std_msgs/msg/String": [],
    "sensor_msgs/msg/Image": ["builtin_interfaces/msg/Time", "std_msgs/msg/Header"],
    "geometry_msgs/msg/TwistStamped": ["builtin_interfaces/msg/Time", "std_msgs/msg/Header", "geometry_msgs/msg/Vector3", "geometry_msgs/msg/Twist"],
    "diagnostic_msgs/msg/DiagnosticArray": [
        "builtin_interfaces/msg/Time",
        "std_msgs/msg/Header",
        "diagnostic_msgs/msg/KeyValue",
        "diagnostic_msgs/msg/DiagnosticStatus",
    ],
    "lifecycle_msgs/srv/GetState": ["lifecycle_msgs/msg/State"],
    "lifecycle_msgs/srv/ChangeState": ["lifecycle_msgs/msg/Transition"],
    "lifecycle_msgs/msg/TransitionEvent": ["lifecycle_msgs/msg/Transition", "lifecycle_msgs/msg/State"],
    "rcl_interfaces/srv/SetParameters": [
        "rcl_interfaces/msg/ParameterValue",
        "rcl_interfaces/msg/Parameter",
        "rcl_interfaces/msg/SetParametersResult",
    ],
}


def definition(ros_type: str) -> str:
    pkg, _, name = ros_type.split("/")
    return (SHARE / pkg / "msg" / f"{name}.msg").read_text()


def type_hash(ros_type: str) -> str:
    pkg, _, name = ros_type.split("/")
    return str(json.loads((SHARE / pkg / "msg" / f"{name}.json").read_text())["type_hashes"][0]["hash_string"])


def prepare(port: int, ros_type: str) -> None:
    from zenoh_ros2_sdk.session import ZenohSession

    session = ZenohSession.get_instance("127.0.0.1", port)
    for dep in DEPENDENCIES[ros_type]:
        session.register_message_type(definition(dep), dep)


def out(record: dict[str, object]) -> None:
    print(json.dumps(record), flush=True)


def until_stdin_closes() -> threading.Event:
    closed = threading.Event()

    def read() -> None:
        sys.stdin.read()
        closed.set()

    threading.Thread(target=read, daemon=True).start()
    return closed


def talk(port: int, topic: str, ros_type: str) -> None:
    from zenoh_ros2_sdk import ROS2Publisher

    prepare(port, ros_type)
    pub = ROS2Publisher(
        topic, ros_type, msg_definition=definition(ros_type), node_name="sdk_talker", router_port=port, type_hash=type_hash(ros_type)
    )
    out({"ready": True})
    closed = until_stdin_closes()
    i = 0
    while not closed.wait(0.02) and i < 2000:
        i += 1
        if ros_type == "std_msgs/msg/String":
            pub.publish(data=f"hello {i}")
        elif ros_type == "geometry_msgs/msg/TwistStamped":
            from zenoh_ros2_sdk.session import ZenohSession

            types = ZenohSession.get_instance("127.0.0.1", port).store.types
            header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=i, nanosec=5), frame_id="base")
            zero = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
            twist = types["geometry_msgs/msg/Twist"](linear=types["geometry_msgs/msg/Vector3"](x=float(i % 2), y=0.0, z=0.0), angular=zero)
            pub.publish(header=header, twist=twist)
        else:
            from zenoh_ros2_sdk.session import ZenohSession

            store = ZenohSession.get_instance("127.0.0.1", port).store
            header = store.types["std_msgs/msg/Header"](stamp=store.types["builtin_interfaces/msg/Time"](sec=i, nanosec=5), frame_id="cam")
            import numpy as np

            data = np.arange(2 * 3 * 3, dtype=np.uint8)  # 2 rows, 3 pixels of RGB
            pub.publish(header=header, height=2, width=3, encoding="rgb8", is_bigendian=0, step=9, data=data)
    pub.close()


def listen(port: int, topic: str, ros_type: str, durability: str = "volatile") -> None:
    from zenoh_ros2_sdk import ROS2Subscriber
    from zenoh_ros2_sdk.qos import QosDurability, QosProfile

    prepare(port, ros_type)

    def received(msg: object) -> None:
        if ros_type == "std_msgs/msg/String":
            out({"data": msg.data})  # type: ignore[attr-defined]
        elif ros_type == "diagnostic_msgs/msg/DiagnosticArray":
            statuses = [
                {"name": s.name, "level": s.level[0] if isinstance(s.level, bytes) else int(s.level), "message": s.message,
                 "hardware_id": s.hardware_id, "values": {kv.key: kv.value for kv in s.values}}
                for s in msg.status  # type: ignore[attr-defined]
            ]  # fmt: skip
            out({"statuses": statuses})
        else:
            out(
                {
                    "encoding": msg.encoding,  # type: ignore[attr-defined]
                    "height": int(msg.height),  # type: ignore[attr-defined]
                    "width": int(msg.width),  # type: ignore[attr-defined]
                    "step": int(msg.step),  # type: ignore[attr-defined]
                    "data": [int(b) for b in msg.data],  # type: ignore[attr-defined]
                    "stamp": [int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)],  # type: ignore[attr-defined]
                }
            )

    qos = QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=1) if durability == "transient_local" else None
    sub = ROS2Subscriber(
        topic,
        ros_type,
        received,
        msg_definition=definition(ros_type),
        node_name="sdk_listener",
        router_port=port,
        type_hash=type_hash(ros_type),
        qos=qos,
    )
    out({"ready": True})
    until_stdin_closes().wait(60)
    sub.close()


def info(port: int, topic: str) -> None:
    from zenoh_ros2_sdk.discovery import get_topic_info, get_topic_names_and_types

    deadline = time.monotonic() + 20
    while True:
        found = get_topic_info(topic, router_port=port, verbose=True)
        if (found is not None and found.publisher_count) or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    publishers = [
        {"node": p.node_name, "namespace": p.node_namespace, "type": p.topic_type, "hash": p.type_hash, "qos": p.qos}
        for p in (found.publishers if found else [])
    ]
    out({"topics": get_topic_names_and_types(router_port=port), "publishers": publishers})


def srv_parts(srv_type: str) -> tuple[str, str, str]:
    """(request definition, response definition, the service type's hash) from ROS 2's own files."""
    pkg, _, name = srv_type.split("/")
    text = (SHARE / pkg / "srv" / f"{name}.srv").read_text()
    # the SDK's parser (rosbags) would take a bare type in a .srv for pkg/srv/msg/Type: qualify it
    text = re.sub(r"^([A-Z][A-Za-z0-9]*)(\[\]|\s)", rf"{pkg}/msg/\1\2", text, flags=re.MULTILINE)
    request, response = re.split(r"^---\s*$", text, maxsplit=1, flags=re.MULTILINE)
    return request, response, str(json.loads((SHARE / pkg / "srv" / f"{name}.json").read_text())["type_hashes"][0]["hash_string"])


def serve(port: int, service: str, srv_type: str) -> None:
    from zenoh_ros2_sdk import ROS2ServiceServer

    prepare(port, srv_type)
    request, response, type_hash = srv_parts(srv_type)
    server: ROS2ServiceServer | None = None

    def answer(msg: object) -> object:
        assert server is not None
        cls = server.response_msg_class
        if srv_type.endswith("/GetState"):
            out({"request": {}})
            state = server.session_mgr.store.types["lifecycle_msgs/msg/State"](id=3, label="active")
            return cls(current_state=state)
        out({"request": {"transition": {"id": int(msg.transition.id), "label": str(msg.transition.label)}}})  # type: ignore[attr-defined]
        return cls(success=int(msg.transition.id) == 3)  # type: ignore[attr-defined]

    server = ROS2ServiceServer(
        service, srv_type, answer, request_definition=request, response_definition=response, node_name="sdk_server", router_port=port, type_hash=type_hash
    )
    out({"ready": True})
    until_stdin_closes().wait(60)
    server.close()


def call(port: int, service: str, srv_type: str, fields: str) -> None:
    from zenoh_ros2_sdk import ROS2ServiceClient

    prepare(port, srv_type)
    request, response, type_hash = srv_parts(srv_type)
    client = ROS2ServiceClient(
        service, srv_type, request_definition=request, response_definition=response, node_name="sdk_client", router_port=port, type_hash=type_hash, timeout=5.0
    )
    out({"ready": True})
    given = json.loads(fields)
    if "transition" in given:
        store = client.session_mgr.store
        given["transition"] = store.types["lifecycle_msgs/msg/Transition"](id=given["transition"]["id"], label=given["transition"].get("label", ""))
    got = None
    deadline = time.monotonic() + 20
    while got is None and time.monotonic() < deadline:  # until the server's queryable is known here
        got = client.call(**given)
    if got is None:
        out({"response": None})
    elif srv_type.endswith("/GetState"):
        out({"response": {"current_state": {"id": int(got.current_state.id), "label": str(got.current_state.label)}}})  # type: ignore[attr-defined]
    else:
        out({"response": {"success": bool(got.success)}})  # type: ignore[attr-defined]
    client.close()


# lifecycle_msgs: the primary states, and the transitions (id -> (label, from, to)) a node takes
_STATES = {1: "unconfigured", 2: "inactive", 3: "active", 15: "errorprocessing"}
_TRANSITIONS = {1: ("configure", 1, 2), 2: ("cleanup", 2, 1), 3: ("activate", 2, 3), 4: ("deactivate", 3, 2)}


def lifecycle(port: int, name: str, topic: str) -> None:
    from zenoh_ros2_sdk import ROS2Publisher, ROS2ServiceServer

    for ros_type in (
        "lifecycle_msgs/srv/GetState", "lifecycle_msgs/srv/ChangeState", "rcl_interfaces/srv/SetParameters", "std_msgs/msg/String",
        "lifecycle_msgs/msg/TransitionEvent",
    ):  # fmt: skip
        prepare(port, ros_type)
    lock = threading.Lock()
    node = {"state": 1, "exposure": 0.1, "stalled": False}
    servers: dict[str, ROS2ServiceServer] = {}
    events = ROS2Publisher(
        f"/{name}/transition_event", "lifecycle_msgs/msg/TransitionEvent", msg_definition=definition("lifecycle_msgs/msg/TransitionEvent"),
        node_name=name, router_port=port, type_hash=type_hash("lifecycle_msgs/msg/TransitionEvent"),
    )  # fmt: skip

    def announce(transition: int, label: str, start: int, goal: int) -> None:  # as rcl_lifecycle publishes each step
        from zenoh_ros2_sdk.session import ZenohSession

        types = ZenohSession.get_instance("127.0.0.1", port).store.types
        state, step = types["lifecycle_msgs/msg/State"], types["lifecycle_msgs/msg/Transition"]
        events.publish(
            timestamp=time.time_ns(), transition=step(id=transition, label=label),
            start_state=state(id=start, label=_STATES[start]), goal_state=state(id=goal, label=_STATES[goal]),
        )  # fmt: skip

    def get_state(msg: object) -> object:
        server = servers["get_state"]
        with lock:
            state = node["state"]
        return server.response_msg_class(current_state=server.session_mgr.store.types["lifecycle_msgs/msg/State"](id=state, label=_STATES[state]))

    def change_state(msg: object) -> object:
        transition = int(msg.transition.id)  # type: ignore[attr-defined]
        label, before, after = _TRANSITIONS.get(transition, ("?", -1, -1))
        with lock:
            ok = node["state"] == before and not (label == "activate" and node.get("refuse_activate"))
            if ok:
                node["state"] = after
        if ok:
            announce(transition, label, before, after)
            out({"transition": label, **({"exposure": node["exposure"]} if label == "configure" else {})})
        return servers["change_state"].response_msg_class(success=ok)

    def set_parameters(msg: object) -> object:
        server = servers["set_parameters"]
        result = server.session_mgr.store.types["rcl_interfaces/msg/SetParametersResult"]
        results = []
        for parameter in msg.parameters:  # type: ignore[attr-defined]
            if parameter.name != "exposure":
                results.append(result(successful=False, reason=f"parameter '{parameter.name}' is not declared"))
            elif int(parameter.value.type) != 3:
                results.append(result(successful=False, reason=f"Wrong parameter type, expected 'Type.DOUBLE' got type {int(parameter.value.type)}"))
            else:
                with lock:
                    node["exposure"] = float(parameter.value.double_value)
                results.append(result(successful=True, reason=""))
        return server.response_msg_class(results=results)

    for suffix, srv_type, handler in (
        ("get_state", "lifecycle_msgs/srv/GetState", get_state),
        ("change_state", "lifecycle_msgs/srv/ChangeState", change_state),
        ("set_parameters", "rcl_interfaces/srv/SetParameters", set_parameters),
    ):
        request, response, srv_hash = srv_parts(srv_type)
        servers[suffix] = ROS2ServiceServer(
            f"/{name}/{suffix}", srv_type, handler, request_definition=request, response_definition=response,
            node_name=name, router_port=port, type_hash=srv_hash,
        )  # fmt: skip
    pub = ROS2Publisher(
        topic, "std_msgs/msg/String", msg_definition=definition("std_msgs/msg/String"), node_name=name, router_port=port,
        type_hash=type_hash("std_msgs/msg/String"),
    )  # fmt: skip
    out({"ready": True})
    closed = threading.Event()

    def read() -> None:
        for line in sys.stdin:
            command = line.strip()
            with lock:
                if command == "fail":  # an error in the node: ErrorProcessing, then (its on_error succeeds) unconfigured
                    node["state"] = 15
                elif command == "stall":
                    node["stalled"] = True
                elif command == "refuse-activate":  # its on_activate fails: it stays inactive
                    node["refuse_activate"] = True
                    out({"command": command})
                elif command == "quiet-fail":  # unconfigured with no transition_event (as if it were lost)
                    node["state"] = 1
            if command == "fail":
                announce(4, "deactivate", 3, 15)
                time.sleep(0.05)
                with lock:
                    node["state"] = 1
                announce(0, "error", 15, 1)
        closed.set()

    threading.Thread(target=read, daemon=True).start()
    i = 0
    while not closed.wait(0.02):
        with lock:
            publishing = node["state"] == 3 and not node["stalled"]
        if publishing:
            i += 1
            pub.publish(data=f"{name} {i}")
    pub.close()
    events.close()
    for server in servers.values():
        server.close()


def main() -> None:
    port, mode, *args = sys.argv[1:]
    {"talk": talk, "listen": listen, "info": info, "serve": serve, "call": call, "lifecycle": lifecycle}[mode](int(port), *args)  # type: ignore[operator]
    from zenoh_ros2_sdk.session import ZenohSession

    ZenohSession.get_instance("127.0.0.1", int(port)).close()


if __name__ == "__main__":
    main()
