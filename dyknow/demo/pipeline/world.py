"""The pipeline robot's world: a 2-D kinematic AUV, the water's visibility, six thrusters and a pipeline.

Pure Python and deterministic: the same :class:`Script` (its seed included) and the same
:class:`Controls` at the same simulated times give the same trajectory and the same
:class:`Measures`, whatever the speed-up. The ROS 2 nodes of :mod:`dyknow.demo.pipeline.robot`
drive it; a test can drive it alone.

The rules (simulated seconds and metres):

- The visibility is a scripted step profile plus seeded Gaussian noise (one draw per tenth of a
  second), clipped to [0, 1]. The seabed can be seen from at most ``DETECT_M_PER_VISIBILITY *
  visibility`` metres of altitude: the spiral altitudes 1, 2 and 3 m (SUAVE's fd_spiral_low,
  medium and high) need a visibility of at least 0.25, 0.5 and 0.75.
- The pipeline lies on the seabed along the line ``y = pipeline_y_m``. The robot starts above
  ``(0, 0)`` and finds it when it can see the seabed and the line is within its camera's swath
  (half-width: its altitude).
- While searching it flies an Archimedean spiral around ``(0, 0)`` whose arms are one swath
  (twice the altitude) apart: searching high covers more ground. While following (the pipeline
  found), it moves onto the line and along +x; the metres flown along the line while it can see
  the seabed are the distance inspected.
- It moves only with the motion controller active and every thruster working, or with the
  controller in its degraded mode (thrust reallocated to the working thrusters: speed scaled by
  their share). Failed thrusters recover together once thruster recovery has been active for
  ``recovery_s``.
"""

from __future__ import annotations

import json
import math
import random
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from dyknow.errors import DyKnowError

__all__ = ["DETECT_M_PER_VISIBILITY", "STEP_S", "THRUSTERS", "Controls", "Measures", "Script", "ScriptError", "World"]

#: The simulation's fixed step (simulated seconds).
STEP_S = 0.05
#: The robot's thrusters, ``thruster_1`` .. ``thruster_6``.
THRUSTERS = 6
#: Metres of altitude from which the seabed can be seen per unit of visibility.
DETECT_M_PER_VISIBILITY = 4.0
#: How fast the robot climbs or dives (m/s).
VERTICAL_M_S = 0.5
#: The noise's resolution: one draw per this many simulated seconds.
NOISE_STEP_S = 0.1


class ScriptError(DyKnowError):
    """A script file is malformed (the message names the file and the field)."""


@dataclass(frozen=True, slots=True)
class Script:
    """What happens in a mission: the visibility's steps ``(from_s, visibility)``, the noise's
    standard deviation, the thruster faults ``(at_s, thruster)``, where the pipeline lies, the
    robot's cruise speed, how long recovery takes, and the seed of the noise."""

    visibility: tuple[tuple[float, float], ...] = ((0.0, 0.6), (40.0, 0.9), (120.0, 0.4), (220.0, 0.8))
    noise: float = 0.02
    faults: tuple[tuple[float, int], ...] = ((180.0, 3), (250.0, 5))
    pipeline_y_m: float = 10.0
    cruise_m_s: float = 1.0
    recovery_s: float = 3.0
    seed: int = 0

    def base_visibility(self, t_s: float) -> float:
        """The scripted step in force at ``t_s`` (before noise)."""
        value = self.visibility[0][1]
        for start, level in self.visibility:
            if start <= t_s:
                value = level
        return value

    def visibility_at(self, t_s: float) -> float:
        """The visibility at ``t_s``: the step plus the noise of its tenth of a second, in [0, 1]."""
        k = int(t_s / NOISE_STEP_S + 1e-9)
        noise = random.Random(self.seed * 1_000_003 + k).gauss(0.0, self.noise) if self.noise > 0 else 0.0
        return min(1.0, max(0.0, self.base_visibility(t_s) + noise))

    @classmethod
    def load(cls, path: str | Path, *, seed: int = 0) -> Script:
        """A script from a JSON file: any of ``visibility`` (``[[from_s, visibility], ...]``),
        ``noise``, ``faults`` (``[[at_s, thruster], ...]``), ``pipeline_y_m``, ``cruise_m_s``,
        ``recovery_s``; the rest as the default script. Raises :class:`ScriptError` naming the
        file and the field."""
        where = str(path)
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except OSError as exc:
            raise ScriptError(f"cannot read it: {exc.strerror or exc}", where=where, expected="a readable JSON file") from exc
        except ValueError as exc:
            raise ScriptError(f"not JSON: {exc}", where=where, expected="a JSON object") from exc
        return cls.from_dict(data, where=where, seed=seed)

    @classmethod
    def from_dict(cls, data: Any, *, where: str = "script", seed: int = 0) -> Script:
        """A script from its JSON object (as :meth:`load` reads it)."""
        if not isinstance(data, dict):
            raise ScriptError(f"got {type(data).__name__}", where=where, expected="a JSON object")
        known = ("visibility", "noise", "faults", "pipeline_y_m", "cruise_m_s", "recovery_s")
        unknown = sorted(set(data) - set(known))
        if unknown:
            raise ScriptError(f"unknown field {unknown[0]!r}", where=where, expected=f"fields among {', '.join(known)}")
        fields: dict[str, Any] = {"seed": seed}

        def number(name: str, low: float, high: float) -> float:
            value = data[name]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
                raise ScriptError(f"{name} = {value!r}", where=where, expected=f"a number from {low} to {high}")
            return float(value)

        def pairs(name: str, check: Any) -> tuple[tuple[float, Any], ...]:
            value = data[name]
            if not isinstance(value, list) or not all(isinstance(p, list) and len(p) == 2 for p in value):
                raise ScriptError(f"{name} = {str(value)[:80]}", where=where, expected="a list of [time_s, value] pairs")
            out = []
            for i, (at, item) in enumerate(value):
                if isinstance(at, bool) or not isinstance(at, (int, float)) or at < 0 or not check(item):
                    raise ScriptError(f"{name}[{i}] = {[at, item]!r}", where=where, expected=f"[time_s >= 0, {check.__doc__}]")
                out.append((float(at), item))
            return tuple(sorted(out, key=lambda p: p[0]))

        def level(v: Any) -> bool:
            """a visibility from 0 to 1"""
            return not isinstance(v, bool) and isinstance(v, (int, float)) and 0 <= v <= 1

        def thruster(v: Any) -> bool:
            """a thruster from 1 to 6"""
            return not isinstance(v, bool) and isinstance(v, int) and 1 <= v <= THRUSTERS

        if "visibility" in data:
            steps = pairs("visibility", level)
            if not steps:
                raise ScriptError("visibility = []", where=where, expected="at least one [from_s, visibility] step")
            fields["visibility"] = tuple((t, float(v)) for t, v in steps)
        if "faults" in data:
            fields["faults"] = pairs("faults", thruster)
        if "noise" in data:
            fields["noise"] = number("noise", 0.0, 1.0)
        if "pipeline_y_m" in data:
            fields["pipeline_y_m"] = number("pipeline_y_m", -1000.0, 1000.0)
        if "cruise_m_s" in data:
            fields["cruise_m_s"] = number("cruise_m_s", 0.01, 10.0)
        if "recovery_s" in data:
            fields["recovery_s"] = number("recovery_s", 0.0, 3600.0)
        return cls(**fields)


@dataclass(frozen=True, slots=True)
class Controls:
    """What the robot's nodes make of the robot now: which lifecycle nodes are active and their
    parameters."""

    motion: bool = False
    max_speed_m_s: float = 1.0
    degraded: bool = False
    search: bool = False
    spiral_altitude_m: float = 1.0
    follow: bool = False
    follow_altitude_m: float = 1.0
    recover: bool = False


@dataclass(frozen=True, slots=True)
class Measures:
    """The mission-level measures SUAVE reports, and what explains them (simulated seconds)."""

    time_to_find_s: float | None
    distance_inspected_m: float
    thruster_faults: int
    thruster_recoveries: int
    time_stopped_s: float
    mission_s: float
    seed: int
    #: faults that struck while thruster recovery was active already: they recover with no switch
    faults_while_recovering: int = 0

    def to_dict(self) -> dict[str, Any]:
        """The measures as JSON (rounded to the millimetre and the millisecond)."""
        out = asdict(self)
        for key, value in out.items():
            if isinstance(value, float):
                out[key] = round(value, 3)
        return out


@dataclass(slots=True)
class World:
    """The simulated robot and its surroundings; :meth:`advance` moves it on."""

    script: Script = field(default_factory=Script)
    t_s: float = 0.0
    x_m: float = 0.0
    y_m: float = 0.0
    altitude_m: float = 1.0
    found_at_s: float | None = None
    inspected_m: float = 0.0
    stopped_s: float = 0.0
    failed: set[int] = field(default_factory=set)
    faults: int = 0
    faults_while_recovering: int = 0
    recoveries: int = 0
    recovering_s: float = 0.0

    @property
    def visibility(self) -> float:
        """The visibility now."""
        return self.script.visibility_at(self.t_s)

    @property
    def found(self) -> bool:
        """Whether the pipeline was found."""
        return self.found_at_s is not None

    def fail(self, thruster: int, *, recovering: bool = False) -> bool:
        """Thruster ``thruster`` fails now (``recovering``: while thruster recovery is active);
        False if it had failed already."""
        if thruster in self.failed:
            return False
        self.failed.add(thruster)
        self.faults += 1
        self.faults_while_recovering += recovering
        return True

    def advance(self, controls: Controls, to_s: float) -> list[tuple[int, bool]]:
        """Step on to ``to_s`` (whole steps of :data:`STEP_S`); returns the thrusters' changes in
        order, ``(thruster, failed)``."""
        changes: list[tuple[int, bool]] = []
        while self.t_s + STEP_S <= to_s + 1e-9:
            changes += self.step(controls)
        return changes

    def step(self, c: Controls) -> list[tuple[int, bool]]:
        """One step of :data:`STEP_S`; returns the thrusters' changes, ``(thruster, failed)``."""
        before, dt = self.t_s, STEP_S
        self.t_s = round(before + dt, 9)
        changes = [(n, True) for at, n in self.script.faults if before <= at < self.t_s and self.fail(n, recovering=c.recover)]  # from its time on
        if self.failed and c.recover:
            self.recovering_s += dt
            if self.recovering_s >= self.script.recovery_s - 1e-9:
                changes += [(n, False) for n in sorted(self.failed)]
                self.recoveries += len(self.failed)
                self.failed.clear()
                self.recovering_s = 0.0
        else:
            self.recovering_s = 0.0
        seeing = self.altitude_m <= DETECT_M_PER_VISIBILITY * self.visibility
        if not self.found and seeing and abs(self.y_m - self.script.pipeline_y_m) <= self.altitude_m:
            self.found_at_s = self.t_s
        if not c.motion or (self.failed and not c.degraded):
            self.stopped_s += dt
            return changes
        speed = min(self.script.cruise_m_s, max(0.0, c.max_speed_m_s)) * (THRUSTERS - len(self.failed)) / THRUSTERS
        following = self.found and c.follow
        target = c.follow_altitude_m if following else c.spiral_altitude_m if c.search else self.altitude_m
        climb = max(-VERTICAL_M_S * dt, min(VERTICAL_M_S * dt, target - self.altitude_m))
        self.altitude_m += climb
        if following:
            off = self.script.pipeline_y_m - self.y_m
            if abs(off) > 1e-6:  # onto the line first
                move = max(-speed * dt, min(speed * dt, off))
                self.y_m += move
            else:
                self.x_m += speed * dt
                if seeing:
                    self.inspected_m += speed * dt
        elif c.search:
            pitch = 2.0 * max(c.spiral_altitude_m, 0.1)  # one swath between the spiral's arms
            b = pitch / (2.0 * math.pi)
            r, phi = math.hypot(self.x_m, self.y_m), math.atan2(self.y_m, self.x_m)
            dphi = speed * dt / math.hypot(r, b)
            r, phi = r + b * dphi, phi + dphi
            self.x_m, self.y_m = r * math.cos(phi), r * math.sin(phi)
        return changes

    def measures(self) -> Measures:
        """The mission's measures so far."""
        return Measures(
            self.found_at_s, self.inspected_m, self.faults, self.recoveries, self.stopped_s, self.t_s, self.script.seed, self.faults_while_recovering
        )
