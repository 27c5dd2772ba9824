"""Configuration models of the hardware backends, one per ``type:``.

Each model is the option set of one backend module in ``appliance/hardware/``; the ``type`` field is the
discriminator of the union in the schema.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from appliance.config.strict import StrictModel


class _Strict(StrictModel):
    """Unknown keys, NaN and infinity refused; integers and booleans strictly typed (see config/strict.py)."""


# --- cameras ------------------------------------------------------------------------------------------


class SimCameraConfig(_Strict):
    """A virtual-rig camera: its optics and pose are in ``virtual_rig.cameras.<name>``."""

    type: Literal["sim"] = "sim"
    frame_delay_ms: float = Field(0.0, ge=0, le=1000, description="Simulated delay per frame (ms).")
    fail_after_frames: int | None = Field(
        None, ge=0, description="Testing: the camera stops delivering after this many frames of a scan."
    )


class AravisCameraConfig(_Strict):
    """A GigE Vision / USB3 Vision camera through Aravis."""

    type: Literal["aravis"] = "aravis"
    address: str | None = Field(None, description="IP address of a GigE camera (e.g. 192.168.3.11).")
    serial: str | None = Field(None, description="Serial number (opened by id; needs discovery).")
    pixel_format: Literal["Mono8", "Mono12", "Mono16"] = "Mono8"
    exposure_us: float = Field(10000.0, gt=0, le=10_000_000, description="Exposure time (µs).")
    gain_db: float = Field(0.0, ge=0, le=48, description="Analogue gain (dB).")
    trigger: Literal["Line1", "Software"] = Field("Line1", description="Hardware line or software trigger.")
    frame_timeout_ms: float = Field(1000.0, gt=0, le=60_000, description="Per-frame timeout after a trigger (ms).")
    packet_size: int | None = Field(None, ge=576, le=9000, description="GigE packet size (bytes); auto when unset.")
    packet_delay_ns: int = Field(0, ge=0, le=1_000_000, description="GigE inter-packet delay (ns).")
    packet_resend: bool = Field(True, description="Ask a GigE camera to resend lost packets.")
    software_trigger: Literal["auto", "external"] = Field(
        "auto",
        description="With trigger: Software, 'auto' fires each frame's trigger as soon as the previous frame "
        "arrived; 'external' waits for the scan to call trigger() once per frame.",
    )
    reconnect_timeout_s: float = Field(
        5.0, ge=0, le=600, description="How long open/arm keep retrying a lost camera, with backoff (s)."
    )


class UvcCameraConfig(_Strict):
    """A V4L2 webcam through OpenCV (software-timed capture)."""

    type: Literal["uvc"] = "uvc"
    device: str = Field("/dev/video0", description="V4L2 device path or index.")
    width: int = Field(1280, ge=16, le=10000, description="Requested width (px).")
    height: int = Field(720, ge=16, le=10000, description="Requested height (px).")
    exposure: float | None = Field(None, description="V4L2 absolute exposure (device units); auto when unset.")
    settle_ms: float = Field(100.0, ge=0, le=5000, description="Wait after each pattern change (ms).")
    flush_frames: int = Field(
        2, ge=0, le=16, description="Stale frames dropped after the settle wait (driver queue)."
    )
    frame_timeout_ms: float = Field(2000.0, gt=0, le=60_000, description="Timeout of one grab (ms).")


CameraConfig = Annotated[
    SimCameraConfig | AravisCameraConfig | UvcCameraConfig, Field(discriminator="type")
]


# --- projectors ---------------------------------------------------------------------------------------


class SimProjectorConfig(_Strict):
    """The virtual rig's projector; optics and pose in ``virtual_rig.projector``."""

    type: Literal["sim"] = "sim"


class VideoOutputConfig(_Strict):
    """The display output wired to the projector's HDMI input (SDL through pygame)."""

    output: str = Field("kmsdrm", description="SDL video driver (kmsdrm needs no desktop).")
    display_index: int = Field(1, ge=0, le=8, description="Which display is the projector's HDMI input.")
    refresh_hz: float = Field(
        60.0, gt=1, le=500, description="Refresh rate of that display (Hz); must match video_frame_period_us."
    )


class LightCrafter4500Config(_Strict):
    """TI DLP LightCrafter 4500 (DLPC350) over USB HID."""

    type: Literal["lightcrafter4500"] = "lightcrafter4500"
    source: Literal["video", "flash"] = Field(
        "video", description="Patterns streamed over HDMI (VSYNC trigger) or already stored in flash."
    )
    exposure_us: int = Field(16667, ge=235, le=2_000_000, description="Pattern exposure (µs).")
    period_us: int = Field(16667, ge=235, le=2_000_000, description="Pattern period (µs).")
    led_current: tuple[int, int, int] = Field((104, 135, 130), description="LED PWM red, green, blue (0-255).")
    trigger_out1_delay_steps: tuple[int, int] = Field((0, 0), description="TRIG_OUT1 rising/falling delay.")
    usb_serial: str | None = Field(None, description="Pick one of several units by USB serial number.")
    video_frame_period_us: int = Field(
        16667, ge=1000, le=1_000_000,
        description="Video source: period of the HDMI input frames (µs); patterns per frame = this // period_us.",
    )
    flash_first_image: int = Field(
        0, ge=0, le=255,
        description="Flash source: flash image index holding the first packed image (see pack_video_frames).",
    )
    video_output: VideoOutputConfig = Field(
        default_factory=VideoOutputConfig,
        description="Video source: the display that feeds the packed images to the projector's HDMI input.",
    )
    video_latency_frames: int = Field(
        1, ge=0, le=4,
        description="Video source: frames from an HDMI frame's arrival to the sequencer showing it (TI documents "
        "one; confirm on the unit).",
    )

    @model_validator(mode="after")
    def _video_frame_period_matches_refresh(self) -> LightCrafter4500Config:
        frame_us = 1e6 / self.video_output.refresh_hz
        if abs(self.video_frame_period_us - frame_us) > 0.01 * frame_us:
            raise ValueError(
                f"video_frame_period_us = {self.video_frame_period_us} disagrees with video_output.refresh_hz = "
                f"{self.video_output.refresh_hz:g} (frames of {frame_us:.0f} µs) by more than 1 %: set "
                f"video_frame_period_us to {round(frame_us)} or refresh_hz to {1e6 / self.video_frame_period_us:.6g}"
            )
        return self


class DisplayProjectorConfig(_Strict):
    """An HDMI/DP projector used as a second display."""

    type: Literal["display"] = "display"
    output: str = Field("kmsdrm", description="SDL video driver or display name.")
    display_index: int = Field(1, ge=0, le=8, description="Which display shows the patterns.")
    refresh_hz: float = Field(60.0, gt=1, le=500, description="Display refresh rate (Hz).")
    latency_frames: int = Field(2, ge=0, le=20, description="Frames between a flip and light on the object.")
    frames_per_pattern: int = Field(2, ge=1, le=60, description="Display frames each pattern stays up.")


ProjectorConfig = Annotated[
    SimProjectorConfig | LightCrafter4500Config | DisplayProjectorConfig, Field(discriminator="type")
]


# --- trigger sources ----------------------------------------------------------------------------------


class SimTriggerConfig(_Strict):
    """A simulated button: pressed from the control socket, ``scan3d trigger`` or Enter in ``scripts/run``."""

    type: Literal["sim"] = "sim"
    stdin: bool = Field(False, description="Enter on standard input presses the button.")


class SerialTriggerConfig(_Strict):
    """The trigger controller on USB serial (SERIAL-PROTOCOL)."""

    type: Literal["serial"] = "serial"
    port: str = Field("/dev/ttyACM0", description="Serial device path (or /dev/serial/by-id/...).")
    baudrate: int = Field(115200, ge=1200, le=4_000_000, description="Baud rate (ignored by USB CDC).")
    pulse_width_us: int = Field(100, ge=1, le=100_000, description="Trigger pulse width (µs).")
    period_us: int = Field(16667, ge=100, le=10_000_000, description="Pulse period of a sequence (µs).")
    heartbeat_timeout_s: float = Field(3.5, gt=0, le=60, description="Link dead after this long without a heartbeat.")
    heartbeat_interval_ms: int = Field(
        1000, ge=10, le=60_000, description="Heartbeat period asked of the controller (ms); ~timeout / 3.5."
    )


class GpioTriggerConfig(_Strict):
    """A button on a GPIO line through libgpiod v2."""

    type: Literal["gpio"] = "gpio"
    chip: str = Field("/dev/gpiochip0", description="GPIO chip device.")
    line: int = Field(17, ge=0, le=1023, description="Line offset on the chip.")
    active_low: bool = Field(True, description="The button pulls the line low.")
    debounce_ms: float = Field(20.0, ge=0, le=1000, description="Debounce period (ms).")


TriggerConfig = Annotated[
    SimTriggerConfig | SerialTriggerConfig | GpioTriggerConfig, Field(discriminator="type")
]
