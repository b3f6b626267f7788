"""Several managers, one system: each knows the others through Zenoh.

Every manager declares a liveliness token on ``@dyknow/<manager>`` and publishes its
:class:`Summary` (host, library, running units, measurements, load) on
``dyknow/<manager>/summary`` whenever it changes; a newcomer asks each manager it discovers
for its summary through the ``get_summary`` service. A :class:`Directory` keeps what the managers
it follows said (the candidates of its plans, those it exchanges data or calls with): one that
appears is noticed when its token does (at once on a reachable network), one that dies or is cut
off when its token goes (its links close, or Zenoh's lease expires); each such token is watched on
its own key, so the others' comings and goings cost it nothing. There is no broker: Zenoh's peers,
gossip and routers carry it all.

A summary arrives from the network, so it is hostile input: it is bounded in size, its specs are
XML read by the hardened spec reader, and nothing in it is ever imported or run here. A
manager's units are only ever spawned by that manager, through its own services and policy.

Its parts: :mod:`~dyknow.federation.summary` (what a manager tells the others, and how it is
read), :mod:`~dyknow.federation.offers` (the tags a manager offers, announced as tokens) and
:mod:`~dyknow.federation.directory` (the managers followed: their liveliness, their summaries,
following and letting go, and what was refused).
"""

from __future__ import annotations

from dyknow.federation.directory import GOODBYE, MAX_CANDIDATES, STOPPED, Directory
from dyknow.federation.offers import MAX_OFFERS, offered
from dyknow.federation.summary import MAX_SUMMARY_BYTES, MAX_SUMMARY_TAGS, Summary, SummaryUnit
from dyknow.federation.summary import peer_specs as peer_specs  # (importable from here as before, outside __all__ as before)
from dyknow.federation.summary import running_units as running_units

__all__ = ["GOODBYE", "MAX_CANDIDATES", "MAX_OFFERS", "MAX_SUMMARY_BYTES", "MAX_SUMMARY_TAGS", "STOPPED", "Directory", "Summary", "SummaryUnit", "offered"]
