"""Lights whose unoccluded contribution at a point has a closed form or a cheap integral, listed by
the adaptive cache's VISIBILITY records: planar polygons of constant radiance (exact irradiance,
:mod:`slc.lib.lights.polygon_lights`; glossy lobes by linearly transformed cosines,
:mod:`slc.lib.lights.polygon_ltc`, or sampled, :mod:`slc.lib.lights.polygon_glossy`), small sphere
lights (:mod:`slc.lib.lights.sphere_lights`) and the bright small regions and sky of an environment
map (:mod:`slc.lib.lights.env_lights`). See docs/adaptive.md."""
