"""The weld as a plan: the seam from a scan, the path the tool takes, the probe's reading and the figures (pure).

The daemon's weld job (:mod:`celld.daemon.weld`) only moves, captures,
reports and records around :mod:`celld.weld.plan`.
"""
