"""One-line device checks for ``scan3d devices``; none of them broadcasts on the network."""

from __future__ import annotations

from appliance.errors import BackendUnavailableError


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
