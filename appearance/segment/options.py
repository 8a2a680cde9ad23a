"""Options of ``damcap segment`` (:class:`SegmentOptions`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal, get_args


from damcap.common.errors import DamcapError
from damcap.common.validate import MAX_COUNT, MAX_IMAGE_SIDE, bounded_int, check_float_fields, require_memory

#: most pixels in one optimisation step
MAX_BATCH_PIXELS = 2 ** 24

from damcap.appearance.dam import DamArchitecture, Encoding


InitColour = Literal["pixel", "darkest-view"]


BRIGHT_FRACTION = 0.02
"""pixels whose mean radiance exceeds this fraction of the radiance scale shape the initial clusters"""


@dataclass(frozen=True)
class SegmentOptions:
    """Options of ``damcap segment``."""

    materials: int = 2
    """number of materials n"""
    steps: int = 1200
    """joint optimisation steps (after the initialisation)"""
    init_steps: int = 300
    """steps that teach Psi the initial (chromaticity k-means) labels and each DAM its cluster"""
    batch_pixels: int = 4096
    """pixels per step"""
    frames_per_step: int = 1
    """training frames Psi sees per step"""
    learning_rate: float = 5e-3
    """Adam learning rate of the DAMs (Psi uses a fifth of it)"""
    sparsity_beta: float = 0.05
    """weight beta of the sparsity cost c_s"""
    prior_weight: float = 1.0
    """weight of the initial labels' cross-entropy during the joint phase (0 = the paper's cost
    alone). The labels are the chromaticity k-means of the same frames, so the fit stays
    unsupervised; keeping them as a soft prior stops the DAMs from trading a material boundary
    for a shading one (measured: bench/segment.md)"""
    illumination_degree: int = 2
    """the initial clustering models the illumination's colour as a polynomial of this degree in
    the world normal (0, 1 or 2; 0 = plain chromaticity k-means): under a tinted environment map
    one material is redder where it faces the sun and bluer where it faces the sky, and plain
    k-means splits it by orientation (measured on the segment-dev captures: bench/segment.md)"""
    init_colour: InitColour = "darkest-view"
    """the colour the initial clustering sees per pixel: 'pixel' (its own) or 'darkest-view' (the
    least bright observation of the same surface point among the training views). Specular
    reflection only adds light and moves with the view, so the darkest observation is the closest
    to the diffuse colour; a material's highlights (tinted by what they reflect) otherwise cluster
    with another material (measured on the segment-dev captures: bench/segment.md)"""
    colour_floor: float = 2e-5
    """pixels whose mean radiance is below this fraction of the radiance scale (the capture's
    95th percentile) show no usable colour and start unlabelled. The clusters are always fitted to
    the pixels above BRIGHT_FRACTION (0.02); dimmer ones down to this floor (e.g. lit only by interreflection) are
    assigned to the nearest cluster"""
    psi_resolution: int = 128
    """Psi runs on frames area-downsampled to at most this many pixels per side; its weights are
    upsampled bilinearly. Speed vs accuracy, measured on the segment-dev captures (128 px): 64
    takes about 0.6x the time of 128 and loses about 0.02 mean IoU (bench/segment.md)"""
    psi_channels: int = 8
    """Psi's base channel count (doubles at each of its two levels)"""
    width: int = 32
    """DAM hidden units"""
    depth: int = 4
    """DAM hidden layers"""
    encoding: Encoding = "nr"
    """DAM input encoding (see DamArchitecture)"""
    seed: int = 0
    """seeds k-means, initialisation and sampling"""
    device: str = "cpu"
    """'cpu', 'cuda' or 'auto'"""

    def validate(self) -> None:
        """Raise DamcapError naming the first bad value (NaN and inf included)."""
        check_float_fields(self)
        if not 1 <= self.materials <= 16:
            raise DamcapError(f"--materials must be between 1 and 16, got {self.materials}")
        for name, lo, hi in (("steps", 1, MAX_COUNT), ("init_steps", 0, MAX_COUNT), ("batch_pixels", 1, MAX_BATCH_PIXELS),
                             ("frames_per_step", 1, 1024), ("psi_resolution", 8, MAX_IMAGE_SIDE), ("psi_channels", 1, 1024)):
            bounded_int(getattr(self, name), lo, hi, f"--{name.replace('_', '-')}")
        # Psi's activations: (frames, 7 * channels, resolution^2) float32 with gradients
        require_memory(float(self.frames_per_step) * 7 * self.psi_channels * self.psi_resolution ** 2 * 4 * 3,
                       f"Psi at --psi-resolution {self.psi_resolution} with --psi-channels {self.psi_channels}")
        if not (self.learning_rate > 0 and self.sparsity_beta >= 0 and self.prior_weight >= 0):
            raise DamcapError(f"--learning-rate must be > 0, --sparsity-beta and --prior-weight >= 0; got "
                              f"{self.learning_rate}, {self.sparsity_beta}, {self.prior_weight}")
        self.architecture  # DAM width and depth within their bounds
        if self.init_colour not in get_args(InitColour):
            raise DamcapError(f"--init-colour must be one of {', '.join(get_args(InitColour))}, got {self.init_colour!r}")
        if not 0 < self.colour_floor <= BRIGHT_FRACTION:
            raise DamcapError(f"--colour-floor must be in (0, {BRIGHT_FRACTION}], got {self.colour_floor}")
        if self.illumination_degree not in (0, 1, 2):
            raise DamcapError(f"--illumination-degree must be 0, 1 or 2, got {self.illumination_degree}")

    @property
    def architecture(self) -> DamArchitecture:
        return DamArchitecture(width=self.width, depth=self.depth, encoding=self.encoding)


def options_json(opts: SegmentOptions) -> dict:
    return asdict(opts)
