"""Algorithms the method folders build on, one package per family: the cone lobes of Surface Light
Cones, their update, shading and packing (:mod:`slc.lib.cones`); the SH basis, YCoCg encodings,
projection and shading from an SH radiance field (:mod:`slc.lib.sh`); lights with closed-form or
cheaply integrated contributions: polygon lights (exact irradiance, LTC and sampled glossy terms),
small sphere lights, an environment map's bright regions and sky (:mod:`slc.lib.lights`).

A method folder (``slc/methods/<folder>/``) keeps its ``Method`` subclass, its update and its state,
and imports these; the library imports core, scene, reference and osc, never a method folder."""
