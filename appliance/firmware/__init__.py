"""Firmware of the trigger controller (MicroPython on an RP2040) and its simulator.

``protocol.py`` and ``controller.py`` are plain Python shared by the board, the host driver
(:mod:`appliance.hardware.serial`) and the simulator; ``main.py`` is the board layer; ``simulate.py`` runs
the same controller under CPython on a pseudo-terminal (``scan3d firmware simulate``).
"""
