"""Which recorded topic plays which role: the twin's commands and outputs in a bag.

The roles are the twin's topics: the commands ``command/displacement`` [m] and
``command/voltage`` [V] and the outputs ``force`` [N] and ``capacitance`` [F], all
``std_msgs/msg/Float64MultiArray`` with one value per unit.  A recorded topic plays a
role if its name ends with it, in any namespace (``/left_array/command/voltage``), or if
it is mapped to it with ``--topic-map OLD=NEW`` (:func:`parse_topic_map`).
:func:`select_topic` picks the topic of one role; :func:`command_topics` and
:func:`output_topics` those of a :class:`~.reader.Bag`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from .reader import Bag, BagError

__all__ = ["command_topics", "output_topics", "parse_topic_map", "select_topic"]

FLOAT_ARRAY = "std_msgs/msg/Float64MultiArray"
COMMANDS = ("displacement", "voltage")
OUTPUTS = ("force", "capacitance")


def parse_topic_map(items: Sequence[str] | None) -> dict[str, str]:
    """``["/rig/disp=command/displacement", ...]`` -> ``{"/rig/disp": "command/displacement"}``.

    OLD is a topic as recorded (a leading ``/`` is added if missing); NEW is the name it
    plays the role of (``command/displacement``, ``force``...) and, for ``--realtime``,
    the name it is republished on.

    Raises
    ------
    BagError
        An item is not ``OLD=NEW``.
    """
    out: dict[str, str] = {}
    for item in items or []:
        old, sep, new = item.partition("=")
        if not sep or not old.strip() or not new.strip():
            raise BagError(f"--topic-map expects OLD=NEW (e.g. /rig/disp=command/displacement), got {item!r}")
        old = old.strip()
        out[old if old.startswith("/") else "/" + old] = new.strip()
    return out


def _plays(name: str, role: str) -> bool:
    name = name.lstrip("/")
    return name == role or name.endswith("/" + role)


def select_topic(topics: dict[str, str], role: str, topic_map: dict[str, str] | None = None,
                 namespace: str | None = None) -> str | None:
    """The recorded topic that plays ``role`` (e.g. ``command/displacement``), or None.

    Topics mapped to the role with ``--topic-map`` come first; otherwise any topic whose
    name ends with the role (``/role`` or ``/ns/role``) and that is not mapped to something
    else.  Among several, the one in ``namespace`` wins.

    Raises
    ------
    BagError
        Several candidates and no way to choose, or the topic has another type.
    """
    topic_map = topic_map or {}
    candidates = [t for t, new in topic_map.items() if t in topics and _plays(new, role)]
    if not candidates:
        candidates = [t for t in topics if t not in topic_map and _plays(t, role)]
    if len(candidates) > 1 and namespace is not None:
        preferred = [t for t in candidates if t == f"{namespace}/{role}"]
        candidates = preferred or candidates
    if len(candidates) > 1:
        raise BagError(f"several topics could be {role}: {', '.join(sorted(candidates))}; choose one with "
                       f"--topic-map {sorted(candidates)[0]}={role}")
    if not candidates:
        return None
    topic = candidates[0]
    if topics[topic] and topics[topic] != FLOAT_ARRAY:
        raise BagError(f"topic {topic} has type {topics[topic]}, expected {FLOAT_ARRAY} for {role}")
    return topic


def command_topics(bag: Bag, topic_map: dict[str, str] | None = None) -> dict[str, str]:
    """``{"displacement": topic, "voltage": topic}`` for the command topics found (at least one).

    Raises
    ------
    BagError
        No command topic, listing the topics present.
    """
    found = {kind: select_topic(bag.topics, f"command/{kind}", topic_map) for kind in COMMANDS}
    found = {k: t for k, t in found.items() if t is not None}
    if not found:
        raise BagError(f"{bag.path}: no command topics (names ending with command/displacement or "
                       f"command/voltage; map others with --topic-map OLD=command/displacement). "
                       f"Topics present:\n{bag.describe_topics()}")
    return found


def output_topics(bag: Bag, commands: dict[str, str], topic_map: dict[str, str] | None = None) -> dict[str, str]:
    """Recorded ``force``/``capacitance`` topics, preferring the commands' namespace."""
    namespace = None
    for kind, topic in commands.items():
        suffix = f"/command/{kind}"
        if topic.endswith(suffix):
            namespace = topic[: -len(suffix)]
    found = {}
    for kind in OUTPUTS:
        try:
            topic = select_topic(bag.topics, kind, topic_map, namespace)
        except BagError as exc:
            print(f"dea-twin: warning: ignoring recorded {kind}: {exc}", file=sys.stderr)
            continue
        if topic is not None:
            found[kind] = topic
    return found
