"""Dataclasses as Dr.Jit structs (slc/core/structs.py): ``DRJIT_STRUCT`` built from the fields."""
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import pytest

import slc.core.backend  # noqa: F401
from slc.core.structs import drjit_struct


@drjit_struct
@dataclass
class _Loop:
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    s: mi.Float = field(default_factory=mi.Float)
    rng: mi.PCG32 | None = None


def test_fields_in_order_and_a_symbolic_loop_carries_them():
    assert _Loop.DRJIT_STRUCT == {"i": mi.UInt32, "s": mi.Float, "rng": mi.PCG32}
    assert list(_Loop.DRJIT_STRUCT) == ["i", "s", "rng"]
    n = dr.arange(mi.UInt32, 5)
    st = _Loop(mi.UInt32(0), mi.Float(0.0), mi.PCG32(5))

    def body(st):
        st.s += mi.Float(st.i)
        st.i += 1
        return (st,)
    st, = dr.while_loop(state=(st,), cond=lambda st: st.i < n, body=body)
    assert dr.all(st.s == mi.Float(n * (n - 1) // 2))        # 0 + 1 + ... + (n - 1) per lane


def test_not_a_dataclass_is_refused():
    with pytest.raises(TypeError, match="not a dataclass"):
        drjit_struct(type("Plain", (), {}))
