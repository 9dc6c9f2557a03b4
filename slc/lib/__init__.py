"""Algorithms shared by the method folders, one package per family: the cone lobes of Surface
Light Cones, their update, shading and packing (:mod:`slc.lib.cones`), and the SH basis, YCoCg
encodings, projection and shading from an SH radiance field (:mod:`slc.lib.sh`).

A method folder (``slc/methods/<folder>/``) keeps its ``Method`` subclass, its update and its state,
and imports these; the library imports the layers below the methods (core, scene, reference, osc),
never a method folder."""
