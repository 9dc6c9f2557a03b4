"""The arrays that the adaptive representations' frozen functions declare as inputs (a frozen
function reads only arrays reachable from its inputs): the sphere lights' and environment
regions' tables (:func:`light_tables`) and the emitter table's arrays (:func:`sampler_inputs`),
shared by the VISIBILITY, CONES and SH updates and shadings.
"""
from __future__ import annotations

import drjit as dr

from slc.methods.adaptive.sampling import sampler_of


def light_tables(sph, env) -> list:
    """The sphere and region tables' arrays (declared as inputs of a frozen function)."""
    out = []
    if env is not None:
        out += env.arrays()
    if sph is not None:
        out += sph.arrays()
    return out


def sampler_inputs(scene) -> list:
    """Every Dr.Jit array of the scene's emitter table (:func:`sampling.sampler_of`,
    which the update uses whatever ``SLC_EMITTER_SAMPLING`` says, with its
    emitter index map): declared as inputs of the frozen update."""
    def arrays(v):
        if isinstance(v, dr.ArrayBase):
            return [v]
        if isinstance(v, (list, tuple)):
            return [a for x in v for a in arrays(x)]
        if isinstance(v, dict):
            return [a for k in sorted(v, key=str) for a in arrays(v[k])]
        return []
    smp = sampler_of(scene)
    return [a for k in sorted(vars(smp)) for a in arrays(vars(smp)[k])]
