"""MegaViews: many-view rendering by concurrent scene-view hierarchy traversal.

Modules: :mod:`.octree` (sparse point octrees), :mod:`.hierarchy` (scene
and view hierarchies), :mod:`.paraboloid` (dual-paraboloid maps),
:mod:`.traversal` (the traversal, ManyLoDs and brute force), :mod:`.maps`
(the depth maps, push, fusion, queries), :mod:`.vpl` (instant radiosity: VPLs, gathering, bilateral
filter), :mod:`.method` (the registered methods). See ``docs/megaviews.md``.

The methods are registered by :mod:`.method` (found by convention, like
every ``slc/methods/<folder>/method.py``).
"""
