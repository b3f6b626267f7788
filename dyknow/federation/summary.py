"""What one manager tells the others: its :class:`Summary` (library, running units, measurements,
load) and how one taken from the network is read, bounded before it is parsed.

A summary arrives from the network, so it is hostile input: it is bounded in size and in tags,
its specs are XML read by the hardened spec reader, its units may offer only keys of their own
manager's key space, and nothing in it is ever imported or run here.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from dyknow import keys
from dyknow.errors import DyKnowError, SpecError
from dyknow.planner import RunningUnit
from dyknow.spec import TransformationSpec, parse_specs

log = logging.getLogger("dyknow.federation")  # one name for the federation, whichever part logs

#: The largest summary a manager takes from another (about 10,000 specs).
MAX_SUMMARY_BYTES = 16 << 20
#: The most tags a summary taken from another manager may carry (its library's and its units'
#: together); a summary with more is refused whole, with a log line naming its manager.
MAX_SUMMARY_TAGS = 65_536

_MAX_ITEMS = 20_000


@dataclass(frozen=True, slots=True)
class SummaryUnit:
    """A running unit as its manager's summary tells: what its outputs carry and where."""

    name: str
    label: str
    outputs: Mapping[str, str]
    tags: Mapping[str, tuple[str, ...]]
    healthy: bool
    owner: str | None = None  # the manager whose request spawned it, if another one

    def running(self, manager: str) -> RunningUnit:
        """The unit as the planner sees it, on ``manager``."""
        return RunningUnit(self.name, self.label, dict(self.outputs), dict(self.tags), self.healthy, manager)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form."""
        return {"name": self.name, "label": self.label, "outputs": dict(self.outputs), "tags": {p: list(t) for p, t in self.tags.items()},
                "healthy": self.healthy, "owner": self.owner}  # fmt: skip


@dataclass(frozen=True, slots=True)
class Summary:
    """What one manager offers the others: its library, its running units, its measurements."""

    manager: str
    host: str
    version: int
    library: str = ""  # changes when the library does (planners cache on it)
    specs: tuple[TransformationSpec, ...] = ()
    units: tuple[SummaryUnit, ...] = ()
    measurements: Mapping[str, float | str] = field(default_factory=dict)
    requests: int = 0
    clock: int = 0  # the manager's clock id (dyknow.message.CLOCK_ID of its process; 0: unknown)

    @property
    def load(self) -> int:
        """How busy the manager is: its running units."""
        return len(self.units)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form, specs as XML (what ``get_summary`` serves and the summary key carries)."""
        return {
            "manager": self.manager,
            "host": self.host,
            "version": self.version,
            "library": self.library,
            "specs": [s.to_xml() for s in self.specs],
            "units": [u.to_dict() for u in self.units],
            "measurements": dict(self.measurements),
            "requests": self.requests,
            "clock": self.clock,
        }

    @classmethod
    def from_json(cls, data: bytes, manager: str, previous: Summary | None = None) -> Summary:
        """A summary received from the network; :class:`DyKnowError` when it is malformed or too big.

        ``manager`` is who it must be about (the key or token it came with). The specs of
        ``previous`` (the last summary of that manager) are kept when its library has not changed,
        so a manager's every unit change does not mean reading its whole library again.
        """
        if len(data) > MAX_SUMMARY_BYTES:
            raise DyKnowError(f"a summary of {len(data)} bytes", where=f"manager {manager!r}", expected=f"at most {MAX_SUMMARY_BYTES}")
        try:
            raw = json.loads(data)
            if not isinstance(raw, dict) or raw.get("manager") != manager:
                raise ValueError("not the summary of this manager")
            specs_xml = raw.get("specs", [])
            units = raw.get("units", [])
            if len(specs_xml) > _MAX_ITEMS or len(units) > _MAX_ITEMS:
                raise ValueError("too many specs or units")
            # its tags counted before any is read (a million of them costs the reader, not the sender)
            tags = sum(len(_TAG.findall(str(xml))) for xml in specs_xml) + sum(_unit_tags(u) for u in units)
            if tags > MAX_SUMMARY_TAGS:
                raise _TooManyTags(f"a summary offering {tags} tags; expected at most {MAX_SUMMARY_TAGS} (MAX_SUMMARY_TAGS)")
            library = str(raw.get("library", ""))[:128]
            specs: list[TransformationSpec] = []
            if previous is not None and library and previous.library == library:
                specs = list(previous.specs)
            else:
                for i, xml in enumerate(specs_xml):
                    specs.extend(parse_specs(str(xml), f"<summary of {manager}, spec {i}>", max_expansions=1))
            measurements = {
                str(k): v
                for k, v in dict(raw.get("measurements", {})).items()
                if isinstance(v, int | float | str) and not isinstance(v, bool)
            }
            return cls(
                manager=manager,
                host=str(raw.get("host", "")),
                version=int(raw.get("version", 0)),
                library=library,
                specs=tuple(specs),
                units=tuple(_unit(u, manager) for u in units),
                measurements=measurements,
                requests=int(raw.get("requests", 0)),
                clock=_clock(raw.get("clock", 0)),
            )
        except _TooManyTags as exc:
            raise DyKnowError(f"refused {exc}", where=f"manager {manager!r}") from exc
        except (ValueError, TypeError, KeyError, AttributeError, RecursionError, SpecError) as exc:
            raise DyKnowError(f"a malformed summary: {str(exc)[:200]}", where=f"manager {manager!r}") from exc


class _TooManyTags(ValueError):
    """A summary over :data:`MAX_SUMMARY_TAGS`."""


_TAG = re.compile(r"<tag[\s>/]")


def _unit_tags(raw: Any) -> int:
    """How many tags a unit of a summary carries (0 for one of the wrong shape: refused when read)."""
    tags = raw.get("tags") if isinstance(raw, dict) else None
    return sum(len(t) for t in tags.values() if isinstance(t, list)) if isinstance(tags, dict) else 0


def _clock(raw: Any) -> int:
    """A clock id from a summary: a 32-bit unsigned integer."""
    if isinstance(raw, bool) or not isinstance(raw, int) or not 0 <= raw < 1 << 32:
        raise ValueError(f"clock {str(raw)[:40]!r} is not a 32-bit id")
    return raw


def _unit(raw: Any, manager: str) -> SummaryUnit:
    """A unit of ``manager``'s summary. Only its outputs on concrete keys of the manager's own key
    space (``dyknow/<manager>/...``) are kept: a summary may not offer another's stream, or a
    wildcard, as its own (a planner would wire whatever publishes there)."""
    own = keys.manager_prefix(manager)
    outputs = {str(p): str(k) for p, k in dict(raw["outputs"]).items()}
    kept = {p: k for p, k in outputs.items() if k.startswith(own) and "*" not in k and "@" not in k}  # '*': any wildcard
    if len(kept) < len(outputs):
        log.warning("summary of %r: outputs outside its key space %s** ignored: %s", manager, own, sorted(set(outputs) - set(kept))[:5])
    tags = {str(p): tuple(str(t) for t in ts) for p, ts in dict(raw["tags"]).items() if str(p) in kept}
    owner = raw.get("owner")
    return SummaryUnit(str(raw["name"]), str(raw["label"]), kept, tags, bool(raw["healthy"]), str(owner) if owner else None)


def running_units(peers: Mapping[str, Summary]) -> list[RunningUnit]:
    """Every unit running on the given managers, as the planner sees them."""
    return [u.running(m) for m, s in sorted(peers.items()) for u in s.units]


def peer_specs(peers: Mapping[str, Summary]) -> dict[str, Sequence[TransformationSpec]]:
    """Each manager's library, by manager."""
    return {m: s.specs for m, s in peers.items()}
