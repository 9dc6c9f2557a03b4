"""Render nodes that share one surface cache: entry owners, sparse record updates, the
strategies compared by ``slc run distributed`` (docs/distributed.md)."""

# sparse updates: a record is sent again when its entry changed by more than this
# (PayloadMethod.record_change); chosen by measurement in docs/distributed.md, "The threshold"
DEFAULT_THRESHOLD = 0.065
# sparse updates: a node stays subscribed to an entry this many frames after its viewers last
# needed it (docs/distributed.md, "The threshold")
DEFAULT_LEASE = 8
