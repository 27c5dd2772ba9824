"""Procedures that drive a rig for something other than a scan: live calibration, verification scans.

They sit above ``hardware/`` and ``scan.py`` (like ``scan.py`` itself); ``calibration/`` keeps the numerics,
board detection and reports and imports neither. Entry points are coroutines: the event loop is started by
the command line (``appliance.cli``) or the service, never here.
"""
