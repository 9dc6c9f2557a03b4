"""Dataclasses of Dr.Jit arrays as Dr.Jit structs (loop state, kernel inputs).

A symbolic loop (``dr.while_loop``) or a frozen function carries a Dr.Jit struct field by
field; the struct names its fields in ``DRJIT_STRUCT``. :func:`drjit_struct` builds that
mapping from the dataclass's own fields, so each field is declared once::

    @drjit_struct
    @dataclass
    class HitLoop:
        t: mi.UInt32 = field(default_factory=mi.UInt32)
        y: mi.Point3f = field(default_factory=mi.Point3f)
"""
from __future__ import annotations

import dataclasses
import types
import typing


def drjit_struct(cls):
    """``cls`` (a dataclass) with ``DRJIT_STRUCT``: its fields in order, each with the type of
    its annotation (``T | None``: ``T``)."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"drjit_struct: {cls.__name__} is not a dataclass (put @drjit_struct above @dataclass)")
    hints = typing.get_type_hints(cls)
    cls.DRJIT_STRUCT = {f.name: _strip_none(hints[f.name]) for f in dataclasses.fields(cls)}
    return cls


def _strip_none(tp):
    if isinstance(tp, types.UnionType) or typing.get_origin(tp) is typing.Union:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return tp
