"""Test doubles shipped with the appliance: a fake GigE Vision camera and a fake DLPC350 (LightCrafter 4500).

They drive the real :mod:`appliance.hardware` backends end to end (the Aravis stack over a private network
namespace, pyusb's backend interface) for tests and for integrators (``scan3d simulate-camera``). Nothing in
the product imports them; only the command line does, for that tool (``tests/test_layering.py`` keeps it so).
"""
