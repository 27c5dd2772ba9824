"""The backend registry: one table (:data:`BACKENDS`) from a device's role and config ``type:`` to how it is
made and checked; :func:`build_rig`, ``scan3d devices`` and ``scan3d grab`` all read it.

Backends are imported lazily, so a missing optional library (gi/Aravis, pyusb, gpiod, pygame) disables only
its own backend, with a message that says what to install.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

from appliance.config.schema import AppConfig
from appliance.errors import BackendUnavailableError
from appliance.hardware import devices_probe as probes
from appliance.hardware.base import Camera, Projector, TriggerSource

if TYPE_CHECKING:
    from appliance.hardware.sim import SimWorld
    from appliance.sim.rig import VirtualRig

Role = Literal["camera", "projector", "trigger"]


@dataclass(frozen=True)
class Backend:
    """One hardware backend: the device it is, the config ``type:`` that chooses it, how it is made, what to
    install when its library is missing, and its one-line check for ``scan3d devices``.

    ``make(name, cfg, world)`` creates (does not open) the device; ``world`` is the virtual rig's
    :class:`~appliance.hardware.sim.SimWorld`, given (and needed) only when ``simulated``. ``probe(cfg)`` is the
    text after ``camera NAME:`` / ``projector:`` / ``trigger:``; it never broadcasts on the network.
    """

    role: Role
    type: str
    make: Callable[[str, Any, SimWorld | None], Any]
    probe: Callable[[Any], str]
    install: str = "see README"
    simulated: bool = False


def _import_backend(kind: str, module: str, install: str) -> Any:
    try:
        return importlib.import_module(f"appliance.hardware.{module}")
    except ImportError as exc:
        raise BackendUnavailableError(f"backend {kind!r} is unavailable: {exc}; install it with: {install}") from exc


def _world(world: SimWorld | None) -> SimWorld:
    assert world is not None, "a simulated device needs the virtual rig's world"
    return world


def _sim(role: Role, cls: str, make: Callable[[Any, str, Any, SimWorld], Any], probe: Callable[[Any], str]) -> Backend:
    def build(name: str, cfg: Any, world: SimWorld | None) -> Any:
        from appliance.hardware import sim

        return make(getattr(sim, cls), name, cfg, _world(world))

    return Backend(role, "sim", build, probe, simulated=True)


def _real(role: Role, kind: str, cls: str, install: str, probe: Callable[[Any], str], with_name: bool) -> Backend:
    def build(name: str, cfg: Any, world: SimWorld | None) -> Any:
        backend_cls = getattr(_import_backend(kind, kind, install), cls)
        return backend_cls(name, cfg) if with_name else backend_cls(cfg)

    return Backend(role, kind, build, probe, install)


# Every backend, one row each. Adding one: its module in appliance/hardware/, its config model in
# appliance/config/backends.py (the ``type:`` literal), and a row here (tests/hardware/test_registry.py checks
# that the rows and the config's types agree).
BACKENDS: tuple[Backend, ...] = (
    _sim("camera", "SimCamera", lambda cls, name, cfg, world: cls(name, cfg, world), probes.sim_camera),
    _real(
        "camera",
        "aravis",
        "AravisCamera",
        "apt-get install gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev && pip install 'pygobject<3.51'",
        probes.aravis_camera,
        with_name=True,
    ),
    _real("camera", "uvc", "UvcCamera", "pip install opencv-python-headless", probes.uvc_camera, with_name=True),
    _sim("projector", "SimProjector", lambda cls, name, cfg, world: cls(world), probes.plain),
    _real(
        "projector",
        "lightcrafter4500",
        "LightCrafter4500",
        "pip install pyusb (and apt-get install libusb-1.0-0)",
        probes.lightcrafter,
        with_name=False,
    ),
    _real("projector", "display", "DisplayProjector", "pip install pygame", probes.plain, with_name=False),
    _sim("trigger", "SimTrigger", lambda cls, name, cfg, world: cls(cfg), probes.plain),
    _real("trigger", "serial", "SerialTrigger", "pip install pyserial", probes.serial_trigger, with_name=False),
    _real("trigger", "gpio", "GpioTrigger", "pip install 'gpiod>=2.1'", probes.gpio_trigger, with_name=False),
)
_BY_KEY = {(b.role, b.type): b for b in BACKENDS}


def backend(role: Role, cfg: Any) -> Backend:
    """The backend that the device config ``cfg`` (its ``type:``) chooses for ``role``."""
    return _BY_KEY[(role, cfg.type)]


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
    chosen = [backend("camera", c) for c in cfg.cameras.values()]
    chosen += [backend("projector", cfg.projector), backend("trigger", cfg.trigger)]
    world = None
    virtual = None
    if any(b.simulated for b in chosen):
        from appliance.hardware.sim import SimWorld
        from appliance.sim.rig import VirtualRig

        virtual = VirtualRig(cfg.virtual_rig, keep_truth=False)  # the service renders; truth on request
        world = SimWorld(virtual)
    cameras: dict[str, Camera] = {
        name: backend("camera", c).make(name, c, world) for name, c in cfg.cameras.items()
    }
    projector: Projector = backend("projector", cfg.projector).make("projector", cfg.projector, world)
    trigger: TriggerSource = backend("trigger", cfg.trigger).make("trigger", cfg.trigger, world)
    return Rig(cameras, projector, trigger, virtual)
