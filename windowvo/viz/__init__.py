"""Rerun viewer: live streaming and .rrd recordings."""
