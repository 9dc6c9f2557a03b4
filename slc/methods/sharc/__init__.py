"""SHaRC: a world-space radiance hash grid for indirect light, updated by a few paths per frame and
read at secondary hits by every viewer (:mod:`.method`: the method ``sharc``; the grid is
:mod:`slc.core.hashgrid`)."""
