"""The ball demo across the ROS 2 boundary (dyknow.demo.ros2, ``dyknow demo --ros2``): the robot's
camera is a ROS 2 node outside the manager, the tracked ball goes back to ROS 2, and the same
planning and adaptation (the battery switch) run across the boundary."""

from __future__ import annotations

import io
from pathlib import Path

from dyknow.demo.ball import BallDemo, Battery


def test_the_ros2_variant_closes_the_loop_and_adapts_across_the_boundary(tmp_path: Path) -> None:
    out = io.StringIO()
    demo = BallDemo(
        duration_s=10.0,
        out_dir=tmp_path,
        stream=out,
        live=False,
        battery=Battery(low_at_s=5.0, charge_at_s=6.0, charge_rate=0.3),
        ros2=True,
    )
    summary = demo.run()["summary"]
    ros2 = summary["ros2"]
    assert ros2["frames_published"] > 100  # 20 frames a second from the ROS 2 camera node
    assert ros2["tracks_received"] > 30  # tracks back in the ROS 2 node, as PointStamped
    assert summary["track_messages"] >= ros2["tracks_received"] - 5
    # the adaptation loop moves the request off the ROS 2 camera (its requirement or the battery),
    # as in the plain demo, and the stream goes on on the same key
    switches = [a for a in summary["adaptations"] if a["kind"] == "recovered"]
    assert any("robot-camera" in a["from"] and "ceiling-camera" in a["to"] for a in switches), summary["adaptations"]
    assert not any("publishers" in a["cause"] for a in summary["adaptations"])  # the camera stayed up throughout
    assert "the robot camera is a ROS 2 node" in out.getvalue()
