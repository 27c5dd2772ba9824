"""One-line device checks for ``scan3d devices`` (each backend's ``probe`` in the registry's table, and the
Aravis discovery a person asks for by name); none of the checks broadcasts on the network."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from appliance.config.schema import AppConfig
from appliance.errors import BackendUnavailableError, HardwareError


def probe_aravis(address: str) -> str:
    """Ask the GigE Vision camera at ``address`` who it is, without any device discovery.

    Parameters
    ----------
    address : str
        The camera's IPv4 address (host names are refused: Aravis would fall back to discovery).

    Returns
    -------
    str
        One line: model, serial, size, pixel format and trigger sources, or why the camera is unusable.
    """
    from appliance.hardware.aravis import is_ip_address, load_aravis

    label = f"aravis {address}"
    if not is_ip_address(address):
        return f"{label}: not an IPv4 address; give the camera's IP address (discovery is never used here)"
    try:
        aravis, glib = load_aravis()
    except BackendUnavailableError as exc:
        return f"{label}: unavailable: {exc}"
    try:
        camera = aravis.Camera.new(address)
    except glib.Error as exc:
        return f"{label}: not reachable ({exc.message}); check power, cable and the host's subnet"
    try:
        _x, _y, width, height = camera.get_region()
        sources = camera.dup_available_trigger_sources()
        return (
            f"{label}: {camera.get_vendor_name()} {camera.get_model_name()} serial "
            f"{camera.get_device_serial_number()}, {width}x{height} {camera.get_pixel_format_as_string()}, "
            f"trigger sources {'/'.join(sources)}"
        )
    except glib.Error as exc:
        return f"{label}: answers but its features cannot be read ({exc.message})"
    finally:
        del camera


def sim_camera(cfg: Any) -> str:
    """A virtual-rig camera: always there."""
    return "sim (virtual rig) — ok"


def aravis_camera(cfg: Any) -> str:
    """A GigE Vision camera by address (:func:`probe_aravis`); one configured by serial needs discovery."""
    where = f"aravis {cfg.address or cfg.serial} — "
    return where + (probe_aravis(cfg.address) if cfg.address else "by serial: needs --discover")


def uvc_camera(cfg: Any) -> str:
    """A V4L2 camera: whether its device node exists."""
    return f"uvc {cfg.device} — {'present' if Path(cfg.device).exists() else 'absent'}"


def lightcrafter(cfg: Any) -> str:
    """A LightCrafter 4500 on USB: whether it answers."""
    from appliance.hardware.lightcrafter4500 import probe_lightcrafter

    return f"lightcrafter4500 — {probe_lightcrafter()}"


def serial_trigger(cfg: Any) -> str:
    """The trigger controller on a serial port: whether it answers with the right protocol."""
    from appliance.hardware.serial import probe_serial

    return f"serial {cfg.port} — {probe_serial(cfg.port)}"


def gpio_trigger(cfg: Any) -> str:
    """A GPIO line: whether its chip exists."""
    return f"gpio {cfg.chip} line {cfg.line} — {'present' if Path(cfg.chip).exists() else 'absent'}"


def plain(cfg: Any) -> str:
    """A device with nothing to ask: its type."""
    return str(cfg.type)


def discover_aravis() -> list[str]:
    """GigE Vision / USB3 Vision device discovery: BROADCASTS on every network interface.

    Only ``scan3d devices --discover`` calls this, on a person's explicit request; the one test that does runs
    it inside a private network namespace whose only interface is loopback.

    Returns
    -------
    list of str
        One line per device found: id, vendor, model, serial, address.
    """
    from appliance.hardware.aravis import load_aravis

    try:
        aravis, _glib = load_aravis()
    except BackendUnavailableError as exc:
        return [f"unavailable: {exc}"]
    aravis.update_device_list()  # the broadcast; user-requested (a test: only inside its own namespace)
    out = []
    for i in range(aravis.get_n_devices()):
        out.append(
            f"{aravis.get_device_id(i)}: {aravis.get_device_vendor(i)} {aravis.get_device_model(i)} "
            f"serial {aravis.get_device_serial_nbr(i)} at {aravis.get_device_address(i)}"
        )
    return out or ["no device answered"]


async def grab_frames(cfg: AppConfig, camera: str, frames: int, out: Path) -> list[Path]:
    """Grab ``frames`` software-triggered frames from one camera into PNG files in ``out``.

    Parameters
    ----------
    cfg : AppConfig
        The configuration (for configured camera names).
    camera : str
        A configured camera name, or ``aravis:ADDRESS`` for a camera that is not configured.
    frames : int
        How many frames.
    out : Path
        Output folder (created).

    Returns
    -------
    list of Path
        The PNG files written.
    """
    import asyncio

    import cv2

    from appliance.atomic_write import write_files_atomic
    from appliance.config.backends import AravisCameraConfig

    try:
        await asyncio.to_thread(out.mkdir, parents=True, exist_ok=True)
    except (OSError, ValueError) as exc:  # ValueError: a NUL in the path
        raise HardwareError(f"grab: --out {str(out)!r} cannot be created ({getattr(exc, 'strerror', None) or exc}); "
                            "give a folder that can be made") from exc
    if camera.startswith("aravis:"):
        cam_cfg: Any = AravisCameraConfig(address=camera.split(":", 1)[1], trigger="Software")
        name = camera.replace(":", "-")
    elif camera in cfg.cameras:
        cam_cfg, name = cfg.cameras[camera], camera
    else:
        raise HardwareError(
            f"grab: camera {camera!r} is not configured (configured: {sorted(cfg.cameras)}); "
            "use a configured name or aravis:ADDRESS"
        )

    async def grab_all() -> list[npt.NDArray[Any]]:
        from appliance.hardware.registry import backend

        chosen = backend("camera", cam_cfg)
        if chosen.simulated:
            def render() -> list[npt.NDArray[Any]]:  # the rig's scene is built in the thread too (the loop guard)
                from appliance.patterns.sequence import WhiteFrame
                from appliance.sim.rig import VirtualRig

                rig = VirtualRig(cfg.virtual_rig)
                return [rig.render_frame(WhiteFrame(), name) for _ in range(frames)]

            return await asyncio.to_thread(render)
        cam = chosen.make(name, cam_cfg, None)
        try:
            await cam.open()
            return [np.array(await cam.grab()) for _ in range(frames)]
        finally:
            await cam.close()

    def write_pngs(images: list[npt.NDArray[Any]]) -> list[Path]:  # all or none: a failure keeps the old files
        files: dict[str, bytes] = {}
        for i, img in enumerate(images):
            ok, png = cv2.imencode(".png", img)
            if not ok:
                raise HardwareError(f"grab: frame {i} of {name}: the PNG encoder refused it ({img.dtype}, "
                                    f"{img.shape})")
            files[f"{name}_{i:03d}.png"] = png.tobytes()
        return write_files_atomic(out, files)

    return await asyncio.to_thread(write_pngs, await grab_all())
