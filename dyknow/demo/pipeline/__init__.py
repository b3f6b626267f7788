"""The pipeline robot, after SUAVE: an underwater robot inspecting a pipeline, as ROS 2 nodes to be managed.

- :mod:`dyknow.demo.pipeline.world`: the simulation (pure Python, deterministic under a seed);
- :mod:`dyknow.demo.pipeline.robot`: the robot as rclpy nodes, ``python -m dyknow.demo.pipeline.robot``;
- :mod:`dyknow.demo.pipeline.baseline`: the same robot with no managing system (one fixed mode);
- :mod:`dyknow.demo.pipeline.managed`: the same robot managed by dyknow (``pipeline.xml``), beside the baseline;
- ``modes.yaml`` beside them (:data:`MODES_FILE`): the robot's modes in ROS 2 system_modes' format;
- ``pipeline.xml``: the spec dyknow manages the robot with (its systems over ``modes.yaml``).

See ``README.md`` beside this file. rclpy is imported only when the robot runs.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["MODES_FILE"]

#: The robot's modes, in the mode-file format of ROS 2's system_modes package.
MODES_FILE = Path(__file__).with_name("modes.yaml")
