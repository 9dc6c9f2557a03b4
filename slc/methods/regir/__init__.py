"""ReGIR: a world-space hash grid of light reservoirs for direct light, built once per frame for
every viewer (:mod:`.grid`: the hash table; :mod:`.method`: the method ``regir``)."""
