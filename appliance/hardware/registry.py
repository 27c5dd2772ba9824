"""The backend registry: config ``type:`` -> backend object.

Backends are imported lazily, so a missing optional library (gi/Aravis, pyusb, gpiod, pygame) disables only
its own backend, with a message that says what to install.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from appliance.config.schema import AppConfig
from appliance.errors import BackendUnavailableError
from appliance.hardware.base import Camera, Projector, TriggerSource

if TYPE_CHECKING:
    from appliance.sim.rig import VirtualRig

_INSTALL_HINTS = {
    "aravis": "apt-get install gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev && pip install 'pygobject<3.51'",
    "lightcrafter4500": "pip install pyusb (and apt-get install libusb-1.0-0)",
    "display": "pip install pygame",
    "gpio": "pip install 'gpiod>=2.1'",
    "serial": "pip install pyserial",
    "uvc": "pip install opencv-python-headless",
}


def _import_backend(kind: str, module: str) -> Any:
    try:
        return importlib.import_module(f"appliance.hardware.{module}")
    except ImportError as exc:
        raise BackendUnavailableError(
            f"backend {kind!r} is unavailable: {exc}; install it with: {_INSTALL_HINTS.get(kind, 'see README')}"
        ) from exc


@dataclass
class Rig:
    """The devices of one configuration, not yet opened."""

    cameras: dict[str, Camera]
    projector: Projector
    trigger: TriggerSource
    virtual: VirtualRig | None = None  # when any device is simulated: its scene, models and ground truth
    extra: dict[str, Any] = field(default_factory=dict)


def build_rig(cfg: AppConfig) -> Rig:
    """Create (but do not open) the configured cameras, projector and trigger source."""
    world = None
    virtual = None
    needs_sim = cfg.projector.type == "sim" or any(c.type == "sim" for c in cfg.cameras.values())
    if needs_sim:
        from appliance.hardware.sim import SimWorld
        from appliance.sim.rig import VirtualRig

        virtual = VirtualRig(cfg.virtual_rig, keep_truth=False)  # the service renders; truth on request
        world = SimWorld(virtual)
    cameras: dict[str, Camera] = {}
    for name, cam_cfg in cfg.cameras.items():
        if cam_cfg.type == "sim":
            from appliance.hardware.sim import SimCamera

            assert world is not None
            cameras[name] = SimCamera(name, cam_cfg, world)
        elif cam_cfg.type == "aravis":
            cameras[name] = _import_backend("aravis", "aravis").AravisCamera(name, cam_cfg)
        else:
            cameras[name] = _import_backend("uvc", "uvc").UvcCamera(name, cam_cfg)
    projector: Projector
    if cfg.projector.type == "sim":
        from appliance.hardware.sim import SimProjector

        assert world is not None
        projector = SimProjector(world)
    elif cfg.projector.type == "lightcrafter4500":
        projector = _import_backend("lightcrafter4500", "lightcrafter4500").LightCrafter4500(cfg.projector)
    else:
        projector = _import_backend("display", "display").DisplayProjector(cfg.projector)
    trigger: TriggerSource
    if cfg.trigger.type == "sim":
        from appliance.hardware.sim import SimTrigger

        trigger = SimTrigger(cfg.trigger)
    elif cfg.trigger.type == "serial":
        trigger = _import_backend("serial", "serial").SerialTrigger(cfg.trigger)
    else:
        trigger = _import_backend("gpio", "gpio").GpioTrigger(cfg.trigger)
    return Rig(cameras, projector, trigger, virtual)
