"""Which topics of a bag are the sensor's: colour, depth, camera info, pressure and wrench,
chosen by name and type, or named by the user (``--topics``). A Punyo kit bag keeps its
pressure under ``/bubble_<serial>`` apart from the camera's namespace; a lone pressure topic
is paired with the camera and the choice is reported."""

from __future__ import annotations

import re

from bubble_rt.frames import FrameError
from bubble_rt.io.bag_messages import CAMERA_INFO, FLOAT32, IMAGE, ROLES, WRENCH


class BagTopicError(FrameError):
    """The bag's topics do not identify one sensor; the message lists what was found."""


def parse_topics(spec: str | dict[str, str] | None) -> tuple[dict[str, str], str]:
    """(role -> topic, namespace) from ``"color=/a,depth=/b"`` / ``"/bubble_2"`` / a dict."""
    if spec is None or spec == "":
        return {}, ""
    if isinstance(spec, dict):
        return dict(spec), ""
    roles: dict[str, str] = {}
    ns = ""
    for part in (s.strip() for s in spec.split(",")):
        if not part:
            continue
        if "=" in part:
            k, v = (x.strip() for x in part.split("=", 1))
            if k not in ROLES:
                raise BagTopicError(f"--topics: unknown role {k!r}; roles are {', '.join(ROLES)}")
            roles[k] = v
        else:
            ns = part.rstrip("/")
    return roles, ns


def _rank(role: str, topic: str) -> int | None:
    """Pattern rank of a topic for a role (lower is better); None when it does not fit."""
    t = topic.lower()
    if role == "color":
        if "depth" in t or "infra" in t:
            return None
        return 0 if re.search(r"colou?r/image_(rect_)?raw$", t) else (1 if "colo" in t else 2)
    if role == "depth":
        if "aligned_depth_to_colo" in t:
            return 0
        if re.search(r"depth/image_(rect_)?raw$", t):
            return 1
        return 2 if "depth" in t else None
    if role == "info":
        if "depth" in t and "aligned_depth_to_colo" not in t:
            return 2
        return 0 if "colo" in t or "aligned_depth_to_colo" in t else 1
    if role == "pressure":
        return 0 if re.search(r"pressure$", t) else (1 if "pressure" in t else None)
    if role == "wrench":
        return 0
    return None


_ROLE_TYPES = {
    "color": IMAGE,
    "depth": IMAGE,
    "info": CAMERA_INFO,
    "pressure": FLOAT32,
    "wrench": WRENCH,
}


def choose_topics(
    found: dict[str, str],
    spec: str | dict[str, str] | None = None,
    path: str = "bag",
    notes: list[str] | None = None,
) -> dict[str, str]:
    """Role -> topic from ``found`` (topic -> message type); raises BagTopicError listing
    what the bag holds when a required role is missing or ambiguous.

    The camera's topics (colour, depth, info) come from one namespace. The pressure comes
    from the camera's namespace when it has one there; else, as punyo-bubble-kit records it
    (``/bubble_<usb serial>/pressure`` beside ``/bubble_1/...``), the bag's only pressure
    topic is paired with the camera and ``notes`` gets a line saying so. Several pressure
    topics elsewhere are ambiguous: the error lists them."""
    given, ns = parse_topics(spec)
    chosen: dict[str, str] = {}
    problems: list[str] = []
    for role, typ in _ROLE_TYPES.items():
        if role == "pressure" and role not in given:
            _choose_pressure(found, ns, chosen, problems, notes)
            continue
        if role in given:
            t = given[role]
            if t not in found:
                problems.append(f"{role}: topic {t!r} (from --topics) is not in the bag")
            elif found[t] != typ:
                problems.append(f"{role}: topic {t!r} is {found[t]}, expected {typ}")
            else:
                chosen[role] = t
            continue
        cands = [
            (r, t)
            for t, ty in found.items()
            if ty == typ
            and (not ns or t.startswith(ns + "/"))
            and (r := _rank(role, t)) is not None
            and t not in chosen.values()
        ]
        if not cands:
            if role != "wrench":
                problems.append(f"{role}: no {typ} topic" + (f" under {ns}" if ns else ""))
            continue
        best = min(r for r, _ in cands)
        tops = sorted(t for r, t in cands if r == best)
        if len(tops) > 1:
            problems.append(f"{role}: ambiguous, candidates {', '.join(tops)}")
            continue
        chosen[role] = tops[0]
    # One camera: colour and depth share a namespace unless given explicitly.
    if not problems and not ns and not given:
        spaces = {_namespace(chosen[r]) for r in ("color", "depth") if r in chosen}
        if len(spaces) > 1:
            problems.append(
                "the chosen colour/depth topics are in different namespaces "
                f"({', '.join(sorted(spaces))}); pick one camera"
            )
    if problems:
        listing = "\n".join(f"  {t}  [{ty}]" for t, ty in sorted(found.items()))
        raise BagTopicError(
            f"{path}: cannot pick the sensor's topics:\n  - "
            + "\n  - ".join(problems)
            + f"\nthe bag holds:\n{listing}\n"
            "choose with --topics color=...,depth=...,info=...,pressure=...[,wrench=...] "
            "or a namespace, e.g. --topics /bubble_1"
        )
    return chosen


def _choose_pressure(
    found: dict[str, str],
    ns: str,
    chosen: dict[str, str],
    problems: list[str],
    notes: list[str] | None,
) -> None:
    """The pressure topic for the camera in ``chosen`` (see :func:`choose_topics`)."""
    cands = sorted(
        (r, t)
        for t, ty in found.items()
        if ty == FLOAT32 and (r := _rank("pressure", t)) is not None
    )
    cam_ns = ns or (_namespace(chosen["color"]) if "color" in chosen else "")
    local = [(r, t) for r, t in cands if cam_ns and t.startswith(cam_ns + "/")]
    pool = local or cands
    if not pool:
        problems.append(f"pressure: no {FLOAT32} topic")
        return
    best = [t for r, t in pool if r == pool[0][0]]
    if len(best) > 1:
        where = f" under {cam_ns}" if local else (f" (none under {cam_ns})" if cam_ns else "")
        problems.append(
            f"pressure: ambiguous{where}, candidates {', '.join(best)}; choose one with "
            "--topics pressure=..."
        )
        return
    chosen["pressure"] = best[0]
    if not local and cam_ns and notes is not None:
        notes.append(
            f"camera {cam_ns} ({chosen.get('color')}, {chosen.get('depth')}) paired with "
            f"{best[0]}, the bag's only pressure topic (another namespace, as the Punyo kit "
            "records it); choose others with --topics"
        )


def _namespace(topic: str) -> str:
    parts = topic.strip("/").split("/")
    return "/" + parts[0] if len(parts) > 1 else "/"
