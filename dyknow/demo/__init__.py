"""Demos: the ball-tracking scenario (the main one), the scenario across three managers, a latency chain."""

from __future__ import annotations

__all__ = ["run_demo"]


def run_demo(
    *,
    chain: bool = False,
    duration_s: float | None = None,
    robot_video: str | None = None,
    ceiling_video: str | None = None,
    out_dir: str = "dyknow-demo-report",
    hops: int = 5,
    rate_hz: float = 20.0,
    as_json: bool = False,
    distributed: bool = False,
    ui_port: int | None = None,
    standby: bool = True,
    ros2: bool = False,
) -> int:
    """Run a demo; returns an exit code. Imports OpenCV only for the ball demo."""
    if distributed:
        from dyknow.demo.distributed import run_distributed_demo

        return run_distributed_demo(as_json=as_json)
    if chain:
        from dyknow.demo.chain import run_demo as run_chain

        return run_chain(duration_s=duration_s or 6.0, hops=hops, rate_hz=rate_hz, as_json=as_json)
    from dyknow.demo.ball import run_ball_demo

    return run_ball_demo(
        duration_s=duration_s or 30.0,
        robot_video=robot_video,
        ceiling_video=ceiling_video,
        out_dir=out_dir,
        as_json=as_json,
        ui_port=ui_port,
        standby=standby,
        ros2=ros2,
    )
