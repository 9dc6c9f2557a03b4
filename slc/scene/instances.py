"""Instances of Mitsuba XML scenes expanded into the shapes they place.

Exporters write an object that appears several times as one ``shapegroup`` and an
``instance`` per copy, each with its ``to_world`` transform. The on-surface cache gives
entries to the surfaces of placed shapes (meshes and analytic shapes,
:mod:`slc.osc.layout`); an instance is no such surface, and the BSDF table
(:mod:`slc.scene.bsdf_table`) cannot see through it. So an XML scene is loaded with every
instance replaced by copies of its group's shapes, each copy placed by the group shape's own
transform followed by the instance's (Mitsuba applies a ``transform``'s operations in order,
so the instance's are appended), and the groups removed. A copy's ``id`` gets the suffix
``@N`` (N the instance's position in the file), so that ids stay unique.

The expanded scene is the same geometry with the same materials (one exception: Mitsuba's
``sphere`` and ``cylinder`` take no shear or non-uniform scale, so under such an instance they
stay round, with Mitsuba's warning, where the instance would stretch them); the renders of every method
and the ground truth are computed on it. The memory that instancing saves is not saved.
"""
from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from contextlib import contextmanager
from pathlib import Path

import mitsuba as mi


class InstanceError(ValueError):
    """An instance that cannot be expanded (its message names it)."""


def _kind(el) -> str | None:
    return el.get("type") if el.tag == "shape" else None


def _to_world(el):
    return next((c for c in el if c.tag == "transform" and c.get("name") == "to_world"), None)


def has_instances(text: str) -> bool:
    """Whether the XML ``text`` may hold an instance (a cheap test before parsing)."""
    return "instance" in text and "shapegroup" in text


def expand(text: str) -> str:
    """The XML scene ``text`` with every ``instance`` replaced by its group's shapes (see the
    module) and the ``shapegroup`` elements removed; ``text`` itself where it holds none. Raises
    :class:`InstanceError` for an instance of an unknown group and for nested instances."""
    if not has_instances(text):
        return text
    root = ET.fromstring(text)
    parents = [(p, el) for p in root.iter() for el in p]
    groups = {}
    for parent, el in parents:
        if _kind(el) == "shapegroup":
            if any(_kind(c) == "instance" for c in el.iter()):
                raise InstanceError(f"shape group '{el.get('id')}' holds an instance (nested instances)")
            groups[el.get("id")] = el
            parent.remove(el)
    instances = [(p, el) for p, el in parents if _kind(el) == "instance"]
    for n, (parent, el) in enumerate(instances):
        ref = next((c for c in el if c.tag == "ref"), None)
        gid = ref.get("id") if ref is not None else None
        if gid not in groups:
            raise InstanceError(f"instance '{el.get('id') or n}' refers to no shape group ('{gid}')")
        placed = _to_world(el)
        pos = list(parent).index(el)
        parent.remove(el)
        for j, shape in enumerate(c for c in groups[gid] if c.tag == "shape"):
            s = copy.deepcopy(shape)
            if s.get("id"):
                s.set("id", f"{s.get('id')}@{n}")
            if placed is not None:
                tw = _to_world(s)
                if tw is None:
                    tw = ET.Element("transform", {"name": "to_world"})
                    s.append(tw)
                tw.extend(copy.deepcopy(list(placed)))
            parent.insert(pos + j, s)
    return ET.tostring(root, encoding="unicode")


@contextmanager
def resolving_from(folder: Path):
    """Mitsuba's file resolver with ``folder`` first while the block runs (relative file names of a
    scene loaded from a string resolve as if it were loaded from a file in ``folder``)."""
    fr = mi.file_resolver()
    saved = [fr[i] for i in range(len(fr))]
    fr.prepend(str(folder))
    try:
        yield
    finally:
        fr.clear()
        for p in saved:
            fr.append(p)
