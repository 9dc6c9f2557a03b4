"""Render nodes that share one surface cache: entry owners, sparse record updates, the
strategies compared by ``slc run distributed`` (docs/distributed.md)."""
