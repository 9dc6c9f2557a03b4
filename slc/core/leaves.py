"""The arrays inside a frozen function's arguments (:mod:`slc.core.freeze`): the 1-D leaves of
nested arrays, Dr.Jit structs, dataclasses and tuples, their widths, and the widths a Mitsuba
scene brings in (which Dr.Jit keys a recording on, through the registry); widening leaves by
copies of their last element and cutting them back."""
from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi


def leaves(x):
    """The 1-D Dr.Jit arrays of a (nested) array, Dr.Jit struct, dataclass, or a
    list / tuple of them (None: none)."""
    if x is None:
        return
    if isinstance(x, (list, tuple)):
        for v in x:
            yield from leaves(v)
    elif is_dataclass(x):
        for f in dataclasses.fields(x):
            yield from leaves(getattr(x, f.name))
    elif dr.is_struct_v(x) and not dr.is_array_v(x):
        for k in type(x).DRJIT_STRUCT:
            yield from leaves(getattr(x, k))
    elif dr.is_array_v(x) and dr.depth_v(x) > 1:
        for i in range(len(x)):
            yield from leaves(x[i])
    elif dr.is_jit_v(x):
        yield x


def map_leaves(x, f):
    """``x`` (an array, a Dr.Jit struct, a dataclass, or a tuple / list of them)
    with ``f`` applied to each 1-D leaf (structs and nested arrays rebuilt)."""
    if isinstance(x, (list, tuple)):
        return type(x)(map_leaves(v, f) for v in x)
    if is_dataclass(x):
        return dataclasses.replace(x, **{k.name: map_leaves(getattr(x, k.name), f) for k in dataclasses.fields(x)
                                         if k.init})
    if dr.is_struct_v(x) and not dr.is_array_v(x):
        out = type(x)()
        for k in type(x).DRJIT_STRUCT:
            setattr(out, k, map_leaves(getattr(x, k), f))
        return out
    if dr.is_array_v(x) and dr.depth_v(x) > 1:
        return type(x)(*[map_leaves(x[i], f) for i in range(len(x))])
    if dr.is_jit_v(x):
        return f(x)
    return x


def is_tree(x) -> bool:
    """Whether ``x`` is a Dr.Jit array or struct, a dataclass, or a list / tuple of them."""
    if x is None:
        return False
    if isinstance(x, (list, tuple)):
        return all(is_tree(v) for v in x)
    if is_dataclass(x):
        return True
    return dr.is_array_v(x) or dr.is_struct_v(x)


def is_dataclass(x) -> bool:
    return dataclasses.is_dataclass(x) and not isinstance(x, type)


def width(x) -> int:
    return max((dr.width(v) for v in leaves(x)), default=0)


def gather_leaf(x, idx, n: int):
    """Leaf ``x`` of width ``n`` gathered at ``idx`` and evaluated on its own
    (other widths: unchanged). One kernel per leaf: its code depends only on
    the leaf's type, so the kernels made at a first call serve every later
    call, whichever of its inputs happen to be literals."""
    if dr.width(x) != n:
        return x
    y = dr.gather(type(x), x, idx)
    dr.eval(y)
    return y


def pad_leaves(x, n: int, w: int):
    """``x`` with its leaves of width ``n`` widened to ``w`` (copies of element ``n - 1``)."""
    idx = lane_index(n, w)
    return map_leaves(x, lambda v: gather_leaf(v, idx, n))


def cut(out, w: int, n: int):
    """A padded call's output with its leaves of width ``w`` cut to ``n``
    lanes (each leaf on its own, as :func:`gather_leaf`)."""
    idx = lane_index(n, n)
    return map_leaves(out, lambda x: gather_leaf(x, idx, w))


def lane_index(n: int, w: int):
    """Lanes 0 .. w-1 reading lane min(i, n - 1): the padding's and the cut's
    index (``n`` opaque: the same kernel for every width)."""
    return dr.minimum(dr.arange(mi.UInt32, w), dr.opaque(mi.UInt32, n - 1))


def is_scene(a) -> bool:
    return isinstance(a, mi.Scene)


def input_widths(a) -> set:
    """Widths of the Dr.Jit arrays an argument brings into a frozen function:
    its leaves, or for a Mitsuba scene every traversed parameter and the
    per-mesh arrays Mitsuba keeps beside them (face, vertex counts and their
    multiples, area distributions)."""
    return scene_widths(a) if is_scene(a) else {dr.width(v) for v in leaves(a)}


def scene_widths(scene) -> set:
    ws = set()
    params = mi.traverse(scene)
    for k in params.keys():
        try:
            v = params[k]
        except Exception:        # pragma: no cover (a parameter that cannot be read)
            continue
        if dr.is_array_v(v) or dr.is_tensor_v(v):
            ws.add(dr.width(v))
            ws.add(len(dr.ravel(v)) if dr.is_array_v(v) else int(dr.prod(v.shape)))
            if dr.is_tensor_v(v) and len(v.shape) >= 2:
                h, w = int(v.shape[0]), int(v.shape[1])
                ws |= {h, w, h * w, h + 1, w + 1, (h + 1) * w, h * (w + 1)}
    for sh in scene.shapes():
        if sh.is_mesh():
            F, V = int(sh.face_count()), int(sh.vertex_count())
            ws |= {F, V, F + 1, V + 1, 2 * F, 3 * F, 2 * V, 3 * V}
    return ws
