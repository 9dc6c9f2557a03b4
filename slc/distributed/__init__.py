"""Render nodes that share one surface cache: entry owners, the owner protocol between nodes
(one protocol object, :class:`slc.distributed.node.Node`, carried in one process or by Ray
actors), the strategies compared by ``slc run distributed`` (docs/distributed.md)."""

# sparse updates: a record is sent again when its entry changed by more than this
# (slc.distributed.records.RecordCodec.change); chosen by measurement in docs/distributed.md, "The threshold"
DEFAULT_THRESHOLD = 0.065
# sparse updates: a node stays subscribed to an entry this many frames after its viewers last
# needed it (docs/distributed.md, "The threshold")
DEFAULT_LEASE = 8
# latency hiding: update rays per frame a node spends on an entry it waits for
# (docs/distributed.md, "Latency")
DEFAULT_BOOTSTRAP = 4
