"""``dyknow demo``: the ball-tracking demo and its variants."""

from __future__ import annotations

import argparse
import os

from dyknow.cli.common import Commands, UsageError


def cmd_demo(args: argparse.Namespace) -> int:
    """run the ball-tracking demo (the battery runs low midway; the stream adapts)"""
    from dyknow.demo import run_demo

    for video in (args.robot_video, args.ceiling_video):
        if video is not None and not os.path.isfile(video):
            raise UsageError(f"{video}: no such video file; expected a video readable by OpenCV")
    if args.duration is not None and args.duration <= 0:
        raise UsageError(f"--duration: got {args.duration}; expected a positive number of seconds")
    return run_demo(
        chain=args.chain,
        duration_s=args.duration,
        robot_video=args.robot_video,
        ceiling_video=args.ceiling_video,
        out_dir=args.out,
        hops=args.hops,
        rate_hz=args.rate,
        as_json=args.json,
        distributed=args.distributed,
        ui_port=args.ui_port if args.ui else None,
        standby=not args.no_standby,
        ros2=args.ros2,
    )


def add_commands(cmds: Commands) -> None:
    """Add this family's commands to the parser."""

    def demo_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--duration", type=float, default=None, metavar="S", help="how long to run (default 30 s; 6 s with --chain)")
        p.add_argument("--robot-video", metavar="PATH", help="a video for the robot camera instead of the synthetic scene")
        p.add_argument("--ceiling-video", metavar="PATH", help="a video for the ceiling camera instead of the synthetic scene")
        p.add_argument("--out", default="dyknow-demo-report", metavar="DIR", help="where to write the report (default ./dyknow-demo-report)")
        p.add_argument("--chain", action="store_true", help="the latency demo instead: a chain of relays, per-hop latency")
        p.add_argument("--ui", action="store_true", help="serve the interactive tool beside the demo (dyknow ui) and print its URL")
        p.add_argument("--ui-port", type=int, default=8321, metavar="PORT", help="the tool's port with --ui (default 8321; 0: any free port)")
        p.add_argument(
            "--no-standby", action="store_true", help="request the track without a warm standby (switches then build their configuration cold)"
        )
        p.add_argument("--distributed", action="store_true",
                       help="the scenario across three manager processes (robot, field, station): battery drop, then a manager killed")  # fmt: skip
        p.add_argument("--ros2", action="store_true",
                       help="the robot camera as a ROS 2 node (rmw_zenoh) and the tracked ball published back to ROS 2")  # fmt: skip
        p.add_argument("--hops", type=int, default=5, help="relays in the chain (--chain; default 5)")
        p.add_argument("--rate", type=float, default=20.0, metavar="HZ", help="source rate (--chain; default 20 Hz)")

    cmds.command("demo", cmd_demo, demo_options)
