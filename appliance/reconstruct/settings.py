"""What the reconstruction reads of its settings: a plain protocol, so ``reconstruct/`` needs no config schema.

The appliance passes its ``reconstruction:`` section (:class:`appliance.config.schema.ReconstructionConfig`
satisfies this protocol); a notebook may pass any object with these attributes, e.g. a dataclass.
"""

from __future__ import annotations

from typing import Protocol


class ReconstructionSettings(Protocol):
    """Triangulation, filter and noise settings of a :class:`~appliance.reconstruct.pipeline.Reconstructor`.

    Lengths in mm, contrasts in DN (8-bit scale), pixels in px; see ``docs/configuration.md`` for each.
    """

    @property
    def mode(self) -> str:
        """``'projector'``, ``'stereo'`` or ``'both'``."""
        ...

    @property
    def min_depth_mm(self) -> float: ...

    @property
    def max_depth_mm(self) -> float: ...

    @property
    def min_neighbours(self) -> int: ...

    @property
    def max_neighbour_jump_mm(self) -> float | None: ...

    @property
    def neighbour_jump_sigmas(self) -> float: ...

    @property
    def neighbour_jump_footprints(self) -> float: ...

    @property
    def max_sigma_mm(self) -> float | None: ...

    @property
    def camera_read_noise_dn(self) -> float: ...

    @property
    def camera_electrons_per_dn(self) -> float: ...

    @property
    def stereo_max_epipolar_px(self) -> float | None: ...

    @property
    def stereo_drift(self) -> str: ...

    @property
    def normals(self) -> bool: ...

    @property
    def normal_radius_px(self) -> int: ...

    @property
    def min_contrast_dn(self) -> float: ...

    @property
    def relative_contrast(self) -> float: ...

    @property
    def blend_ratio(self) -> float: ...

    @property
    def separate_copies(self) -> bool: ...

    @property
    def hidden_check(self) -> str:
        """``'auto'``, ``'always'`` or ``'off'``: drop points the projector cannot light
        (:mod:`appliance.reconstruct.visibility`)."""
        ...

    @property
    def edge_blur_px(self) -> float:
        """The cameras' blur (camera px) the albedo-edge correction assumes; 0: off
        (:mod:`appliance.reconstruct.albedo_edges`)."""
        ...

    @property
    def indirect_sigma(self) -> bool:
        """Widen a camera-projector point's sigma by the bias of indirect light
        (:func:`appliance.reconstruct.uncertainty.fringe_variance_table`)."""
        ...
