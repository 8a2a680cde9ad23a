"""Options of ``damcap segment`` (:class:`SegmentOptions`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Literal, get_args

from damcap.appearance.dam import DamArchitecture, Encoding
from damcap.common.errors import DamcapError
from damcap.common.validate import (COUNT, COUNT_OR_ZERO, MAX_BATCH_PIXELS, MAX_DAM_DEPTH, MAX_DAM_WIDTH, MAX_IMAGE_SIDE, SEED, check_ranges, in_range, require_memory)

#: most materials a segmentation fits
MAX_SEGMENT_MATERIALS = 16


InitColour = Literal["pixel", "darkest-view"]
PriorMode = Literal["off", "predictor", "auto"]


BRIGHT_FRACTION = 0.02
"""pixels whose mean radiance exceeds this fraction of the radiance scale shape the initial clusters"""


@dataclass(frozen=True)
class SegmentOptions:
    """Options of ``damcap segment``."""

    materials: int = field(default=2, metadata=in_range(1, MAX_SEGMENT_MATERIALS))
    """number of materials n"""
    steps: int = field(default=1200, metadata=COUNT)
    """joint optimisation steps (after the initialisation)"""
    init_steps: int = field(default=300, metadata={**COUNT_OR_ZERO, "cli_panel": "advanced"})
    """steps that teach Psi the initial (chromaticity k-means) labels and each DAM its cluster"""
    batch_pixels: int = field(default=4096, metadata=in_range(1, MAX_BATCH_PIXELS))
    """pixels per step"""
    frames_per_step: int = field(default=1, metadata=in_range(1, 1024, cli_panel="advanced"))
    """training frames Psi sees per step"""
    learning_rate: float = field(default=5e-3, metadata=in_range(0, 10, lo_open=True))
    """Adam learning rate of the DAMs (Psi uses a fifth of it)"""
    sparsity_beta: float = field(default=0.05, metadata=in_range(0, 1e6, cli_panel="advanced"))
    """weight beta of the sparsity cost c_s"""
    prior_weight: float = field(default=1.0, metadata=in_range(0, 1e6, cli_panel="advanced"))
    """weight of the initial labels' cross-entropy during the joint phase (0 = the paper's cost
    alone). The labels are the chromaticity k-means of the same frames, so the fit stays
    unsupervised; keeping them as a soft prior stops the DAMs from trading a material boundary
    for a shading one (measured: bench/segment.md)"""
    illumination_degree: int = field(default=2, metadata=in_range(0, 2, cli_panel="advanced"))
    """degree of the polynomial in the world normal that models the illumination's colour in the
    initial clustering (0 = plain chromaticity k-means). Under a tinted environment map one
    material is redder where it faces the sun and bluer where it faces the sky, and plain k-means
    splits it by orientation (measured on the segment-dev captures: bench/segment.md)."""
    init_colour: InitColour = field(default="darkest-view", metadata={"cli_panel": "advanced"})
    """the colour the initial clustering sees per pixel: 'pixel' (its own) or 'darkest-view' (the
    least bright observation of the same surface point among the training views). Specular
    reflection only adds light and moves with the view, so the darkest observation is the closest
    to the diffuse colour; a material's highlights (tinted by what they reflect) otherwise cluster
    with another material (measured on the segment-dev captures: bench/segment.md)"""
    colour_floor: float = field(default=2e-5, metadata=in_range(0, BRIGHT_FRACTION, lo_open=True, cli_panel="advanced"))
    """pixels whose mean radiance is below this fraction of the radiance scale (the capture's
    95th percentile) show no usable colour and start unlabelled. The clusters are always fitted to
    the pixels above BRIGHT_FRACTION (0.02); dimmer ones down to this floor (e.g. lit only by interreflection) are
    assigned to the nearest cluster"""
    psi_resolution: int = field(default=128, metadata=in_range(8, MAX_IMAGE_SIDE, cli_panel="advanced"))
    """Psi runs on frames area-downsampled to at most this many pixels per side; its weights are
    upsampled bilinearly. Speed vs accuracy, measured on the segment-dev captures (128 px): 64
    takes about 0.6x the time of 128 and loses about 0.02 mean IoU (bench/segment.md)"""
    psi_channels: int = field(default=8, metadata=in_range(1, 1024, cli_panel="advanced"))
    """Psi's base channel count (doubles at each of its two levels)"""
    width: int = field(default=32, metadata=in_range(1, MAX_DAM_WIDTH))
    """DAM hidden units"""
    depth: int = field(default=4, metadata=in_range(1, MAX_DAM_DEPTH))
    """DAM hidden layers"""
    encoding: Encoding = field(default="nr", metadata={"cli_panel": "advanced"})
    """DAM input encoding (see DamArchitecture)"""
    prior: PriorMode = field(default="predictor", metadata={"cli_what": "prior"})
    """a prior on each material's DAM: 'off', 'predictor' (each material's DAM starts from the
    shipped predictor's prediction for the pixels first assigned to it, and that prediction pulls
    it where those pixels constrain it least: appearance/segment/prior.py) or 'auto' (segment
    without and with it on the training views but an arc of held-out ones, keep the mode whose
    held-out views score the lower DSSIM, then segment all views with it: three segmentations).
    On the rendered studio capture (3 materials, the other camera ring novel) 'predictor'
    lowered novel-view DSSIM from 0.278 to 0.271 (lower on each of 3 seeds), on a closed-form
    torus from 0.106 to 0.089; on the real cape 0.428 against 0.427 (bench/segment_prior.md)"""
    prior_dam_weight: float = field(default=1.0, metadata=in_range(0, 1e6, cli_panel="advanced"))
    """--prior predictor: weight of the prediction's cost against the data cost (both L1 of
    radiance / scale; each material's weighted by its share of the pixels)"""
    prior_sigma: float = field(default=0.25, metadata=in_range(0, 10, lo_open=True, cli_panel="advanced"))
    """--prior predictor: distance in the DAM's input encoding over which a material's pixels take
    over from its prediction (a sample that far from every pixel of the material has weight 0.63)"""
    prior_samples: int = field(default=32768, metadata={**COUNT, "cli_panel": "advanced"})
    """--prior predictor: (view, normal) samples per material, drawn once over its pixels' normals
    and their hemispheres"""
    prior_holdout_views: int = field(default=2, metadata={**COUNT, "cli_panel": "advanced"})
    """--prior auto: training views held out to decide (an arc of neighbouring cameras farthest
    from the others, as fit's --holdout arc)"""
    seed: int = field(default=0, metadata=SEED)
    """seeds k-means, initialisation and sampling"""
    device: str = "cpu"
    """'cpu', 'cuda' or 'auto'"""

    def validate(self) -> None:
        """Raise DamcapError naming the first bad value (NaN and inf included)."""
        check_ranges(self)
        # Psi's activations: (frames, 7 * channels, resolution^2) float32 with gradients
        require_memory(float(self.frames_per_step) * 7 * self.psi_channels * self.psi_resolution ** 2 * 4 * 3,
                       f"Psi at --psi-resolution {self.psi_resolution} with --psi-channels {self.psi_channels}")
        self.architecture  # DAM width and depth within their bounds
        if self.init_colour not in get_args(InitColour):
            raise DamcapError(f"--init-colour must be one of {', '.join(get_args(InitColour))}, got {self.init_colour!r}")
        if self.prior not in get_args(PriorMode):
            raise DamcapError(f"--prior must be one of {', '.join(get_args(PriorMode))}, got {self.prior!r}")

    @property
    def architecture(self) -> DamArchitecture:
        return DamArchitecture(width=self.width, depth=self.depth, encoding=self.encoding)


def options_json(opts: SegmentOptions) -> dict:
    return asdict(opts)
