"""scan3d: a structured-light 3D scanner appliance."""

__version__ = "0.1.0"
