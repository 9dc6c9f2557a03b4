"""Path tracing: the equal-time GI baseline."""
