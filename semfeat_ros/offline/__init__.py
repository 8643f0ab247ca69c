"""Offline batch tools: bag reading, front ends, mapping runs, metrics and figures."""
