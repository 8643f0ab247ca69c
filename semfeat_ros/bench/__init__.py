"""Measurements of ``semfeat-bench`` (:mod:`semfeat_ros.tools.bench` is its command line):
:mod:`.stats`, :mod:`.machine`, :mod:`.frames`, :mod:`.stages`, :mod:`.pipeline`,
:mod:`.document`."""
