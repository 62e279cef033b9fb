"""The weld as a plan and as a process (pure): the seam from a scan, the path the tool takes, the probe's
reading and the figures (:mod:`celld.weld.plan`); the weld procedures (:mod:`celld.weld.procedure`); what the
arc did and the weld data against the procedure's windows (:mod:`celld.weld.arc_report`,
:mod:`celld.weld.weld_data`).

The daemon's weld job (:mod:`celld.daemon.weld`) only moves, captures,
reports and records around them.
"""
